"""Loaded by every Python process a test starts with this folder first on ``PYTHONPATH`` (the
memlog command and its worker processes): each chunk an MCAP reader reads from a log itself — a
pass's read or the scan's — is appended, as ``pid offset path``, to the file named by
``MEMLOG_TEST_CHUNK_READS``. ``tests/test_spool.py`` counts them across processes (no strace)."""

import os

_OUT = os.environ.get("MEMLOG_TEST_CHUNK_READS")
if _OUT:
    from memlog.io.mcap import reader as _reader
    from memlog.io.mcap import scan as _scan

    def _note(path: str, offset: int) -> None:
        fd = os.open(_OUT, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, f"{os.getpid()} {offset} {os.path.realpath(path)}\n".encode())
        finally:
            os.close(fd)

    _now = _reader.McapLog._read_chunk_now
    _scanned = _scan.DataScan._read_chunk

    def _read_chunk_now(self, ref):  # type: ignore[no-untyped-def]
        _note(self.path, ref.offset)
        return _now(self, ref)

    def _read_chunk(self, pos, n):  # type: ignore[no-untyped-def]
        _note(self.log.path, pos)
        return _scanned(self, pos, n)

    _reader.McapLog._read_chunk_now = _read_chunk_now
    _scan.DataScan._read_chunk = _read_chunk

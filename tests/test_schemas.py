"""The definitions memlog writes: ``schemas/`` is generated from memlog.outputs.schemas, and the
Foxglove definitions in memlog/outputs/foxglove/ are exactly what tools/foxglove_schemas.py makes
of the pinned @foxglove/schemas release."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import re
import shutil
import subprocess
import tempfile
from pathlib import Path
from types import ModuleType

import pytest
from google.protobuf import descriptor_pb2

from memlog.outputs.schemas import FOXGLOVE_DIR, MESSAGES, generated_files, proto_descriptor_set, proto_file
from tests.conftest import ROOT, skip_or_fail

SCHEMAS_DIR = ROOT / "schemas"


def _tools() -> ModuleType:
    spec = importlib.util.spec_from_file_location("foxglove_schemas", ROOT / "tools" / "foxglove_schemas.py")
    assert spec and spec.loader
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _files(base: Path) -> dict[str, bytes]:
    return {str(p.relative_to(base)): p.read_bytes() for p in sorted(base.rglob("*")) if p.is_file()}


def test_schema_files_are_up_to_date() -> None:
    want = generated_files()
    have = _files(SCHEMAS_DIR)
    assert sorted(have) == sorted(want), "run python -m memlog.outputs.schemas schemas (and remove stale files)"
    for rel, data in want.items():
        assert have[rel] == data, f"schemas/{rel} is stale: run python -m memlog.outputs.schemas schemas"


# -- .proto text against descriptors -------------------------------------------------------------------

_SCALARS = {"double", "float", "int32", "int64", "uint32", "uint64", "sint32", "sint64", "fixed32", "fixed64",
            "sfixed32", "sfixed64", "bool", "string", "bytes"}


def _proto_fields(text: str) -> dict[str, list[tuple[str, str, str, int]]]:
    """message -> [(label, type, name, number)] of a generated .proto (one level of nesting: enums)."""
    out: dict[str, list[tuple[str, str, str, int]]] = {}
    body = re.sub(r"//[^\n]*", "", text)
    for m in re.finditer(r"^message (\w+) \{(.*?)^\}", body, flags=re.M | re.S):
        inner = re.sub(r"enum \w+ \{.*?\}", "", m.group(2), flags=re.S)
        out[m.group(1)] = [(lab or "", typ, name, int(num)) for lab, typ, name, num in
                           re.findall(r"(repeated |optional )?([\w.]+) (\w+) = (\d+);", inner)]
    return out


def _descriptor_fields(fds_bytes: bytes, package: str) -> dict[str, list[tuple[str, str, str, int]]]:
    fds = descriptor_pb2.FileDescriptorSet()
    fds.ParseFromString(fds_bytes)
    F = descriptor_pb2.FieldDescriptorProto
    names = {v: k.removeprefix("TYPE_").lower() for k, v in F.Type.items()}
    out: dict[str, list[tuple[str, str, str, int]]] = {}
    for fd in fds.file:
        if fd.package != package:
            continue
        assert fd.syntax == "proto3"
        for mt in fd.message_type:
            fields = []
            for f in mt.field:
                label = "repeated " if f.label == F.LABEL_REPEATED else "optional " if f.proto3_optional else ""
                typ = f.type_name.lstrip(".") if f.type_name else names[f.type]
                if f.type == F.TYPE_ENUM:
                    typ = typ.rsplit(".", 1)[1]  # the .proto names a nested enum without its message
                fields.append((label, typ, f.name, f.number))
            out[mt.name] = fields
    return out


@pytest.mark.parametrize("name", ["FrameScores", "Match"])
def test_memlog_proto_descriptor_matches_its_proto_file(name: str) -> None:
    text = proto_file(name)
    assert _descriptor_fields(proto_descriptor_set(name), "memlog") == _proto_fields(text)
    assert set(_proto_fields(text)) == {name, *(m.name for m in MESSAGES[name].deps())}


def _protoc() -> list[str] | None:
    return _tools().find_protoc()  # type: ignore[no-any-return]


@pytest.mark.parametrize("name", ["FrameScores", "Match"])
def test_memlog_proto_descriptor_is_what_protoc_makes(name: str, tmp_path: Path) -> None:
    protoc = _protoc()
    if protoc is None:
        skip_or_fail("protoc is not installed (apt install protobuf-compiler or pip install grpcio-tools)")
    (tmp_path / "memlog").mkdir()
    (tmp_path / "memlog" / f"{name}.proto").write_text(proto_file(name))
    out = tmp_path / "out.fds"
    subprocess.run([*protoc, f"-I{tmp_path}", "--include_imports", f"--descriptor_set_out={out}",
                    f"memlog/{name}.proto"], check=True)
    a, b = descriptor_pb2.FileDescriptorSet(), descriptor_pb2.FileDescriptorSet()
    a.ParseFromString(out.read_bytes())
    b.ParseFromString(proto_descriptor_set(name))
    assert [f for f in a.file if f.package == "memlog"] == [f for f in b.file if f.package == "memlog"]


# -- the vendored Foxglove definitions -------------------------------------------------------------------

def test_vendored_foxglove_files_match_their_manifest() -> None:
    tools = _tools()
    manifest = json.loads((FOXGLOVE_DIR / "MANIFEST.json").read_text())
    assert (manifest["package"], manifest["version"], manifest["tarball_sha256"]) == (
        tools.PACKAGE, tools.VERSION, tools.TARBALL_SHA256)
    have = _files(FOXGLOVE_DIR)
    assert set(have) == set(manifest["files"]) | {"MANIFEST.json"}
    for rel, digest in manifest["files"].items():
        assert hashlib.sha256(have[rel]).hexdigest() == digest, f"{rel} was edited: run tools/foxglove_schemas.py"


@pytest.mark.parametrize("name", ["ImageAnnotations", "CompressedImage"])
def test_vendored_descriptors_are_the_vendored_proto_files(name: str) -> None:
    """The FileDescriptorSet holds exactly the messages and fields of Foxglove's generated .proto files."""
    fds = (FOXGLOVE_DIR / "fds" / f"foxglove.{name}.fds").read_bytes()
    got = _descriptor_fields(fds, "foxglove")
    want: dict[str, list[tuple[str, str, str, int]]] = {}
    for short in got:
        text = (FOXGLOVE_DIR / "proto" / "foxglove" / f"{short}.proto").read_text()
        want.update(_proto_fields(text))
    assert name in got and got == want
    s = descriptor_pb2.FileDescriptorSet()
    s.ParseFromString(fds)
    assert {f.name for f in s.file} == {f"foxglove/{m}.proto" for m in got} | {"google/protobuf/timestamp.proto"}


def test_official_annotation_schema_has_timestamp_and_metadata() -> None:
    """The hand-written copy memlog used to carry lacked both."""
    schema = json.loads((FOXGLOVE_DIR / "jsonschema" / "foxglove.ImageAnnotations.json").read_text())
    assert {"timestamp", "metadata", "circles", "points", "texts"} <= set(schema["properties"])
    assert schema["$comment"] == "Generated by https://github.com/foxglove/foxglove-sdk"
    msg = (FOXGLOVE_DIR / "ros2msg" / "foxglove_msgs" / "msg" / "ImageAnnotations.msg").read_text()
    assert "builtin_interfaces/Time timestamp" in msg and "foxglove_msgs/KeyValuePair[] metadata" in msg


def test_vendored_foxglove_files_are_what_the_script_generates() -> None:
    """Regenerate from the pinned tarball (npm pack, or $MEMLOG_FOXGLOVE_TARBALL) and compare. Needs node,
    npm and protoc; without them the manifest test above still pins every file's hash."""
    tools = _tools()
    missing = [t for t in ("node",) if shutil.which(t) is None]
    if tools.find_protoc() is None:
        missing.append("protoc")
    local = os.environ.get("MEMLOG_FOXGLOVE_TARBALL")
    if not local and shutil.which("npm") is None:
        missing.append("npm")
    if missing:
        skip_or_fail(f"{', '.join(missing)} not installed: only the recorded hashes are checked")
    with tempfile.TemporaryDirectory() as tmp:
        try:
            tarball = Path(local) if local else tools.fetch_tarball(Path(tmp))
        except tools.GenerateError as exc:
            skip_or_fail(f"cannot fetch the tarball ({exc}); set MEMLOG_FOXGLOVE_TARBALL to a local copy")
        files = tools.generate(tarball)
    assert tools.differences(files) == []

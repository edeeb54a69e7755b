"""The shipped Foxglove layout (``memlog/outputs/foxglove_layout.json``, :mod:`memlog.outputs.layout`).

It is a layout in Foxglove's shape; every topic it names is one that memlog writes, and every message
path it plots or shows resolves in a message of that topic. Both are checked against real outputs, not a
list: ``memlog score`` and ``memlog localize --annotate`` run on the fixtures, and one message of each
topic is decoded by the mcap project's own decoders (as Foxglove decodes them, from the schema in the
file). The demo log is the layout's own camera; the other encoding families (ROS 1, Foxglove JSON and
protobuf) get the layout retargeted to their camera as its docs tell users to. And the file is package
data: a wheel built from the tree carries it, and ``layout_path()`` finds it in the installed copy.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from memlog.outputs.layout import LAYOUT_CAMERA, layout_path
from tests.conftest import FIXTURES, ROOT

#: fixture -> its camera topic: the demo (ROS 2) is the layout's own; the others are one per family
FAMILIES = {
    "demo.mcap": LAYOUT_CAMERA,
    "ros1.bag": "/camera/image_raw",
    "foxglove_json.mcap": "/cam/compressed",
    "foxglove_proto.mcap": "/cam/compressed",
}
PANEL_TYPES = {"Image", "Plot", "StateTransitions", "RawMessages", "Table"}


def _layout(camera: str = LAYOUT_CAMERA) -> dict[str, Any]:
    """The shipped layout, retargeted to ``camera`` the way the module docs say (replace the text)."""
    text = layout_path().read_text(encoding="utf-8")
    return dict(json.loads(text.replace(LAYOUT_CAMERA, camera)))


def _leaves(node: Any) -> Iterator[str]:
    """Panel ids of a mosaic tree (a panel id, or a split with ``first`` and ``second``)."""
    if isinstance(node, str):
        yield node
        return
    assert isinstance(node, dict) and set(node) <= {"first", "second", "direction", "splitPercentage"}, node
    assert node["direction"] in ("row", "column"), node
    assert 0 < node.get("splitPercentage", 50) < 100, node
    yield from _leaves(node["first"])
    yield from _leaves(node["second"])


def _panel_type(panel_id: str) -> str:
    return panel_id.split("!", 1)[0]


def _references(layout: dict[str, Any]) -> list[tuple[str, str, str]]:
    """(panel id, kind, text) of every topic and message path the layout names: kind is ``image``,
    ``annotations`` (topics) or ``path`` (a message path, the topic first)."""
    out = []
    for pid, cfg in layout["configById"].items():
        kind = _panel_type(pid)
        if kind == "Image":
            mode = cfg["imageMode"]
            out.append((pid, "image", mode["imageTopic"]))
            out += [(pid, "annotations", t) for t in mode.get("annotations", {})]
            if mode.get("calibrationTopic"):
                out.append((pid, "calibration", mode["calibrationTopic"]))
        elif kind in ("Plot", "StateTransitions"):
            out += [(pid, "path", p["value"]) for p in cfg["paths"]]
            if cfg.get("xAxisPath"):
                out.append((pid, "path", cfg["xAxisPath"]["value"]))
        elif kind in ("RawMessages", "Table"):
            out.append((pid, "path", cfg["topicPath"]))
            if cfg.get("diffTopicPath"):
                out.append((pid, "path", cfg["diffTopicPath"]))
        else:  # a panel this test does not know: it could not check its topics
            raise AssertionError(f"{pid}: panel type {kind} is not one this test reads")
    return out


_STEP = re.compile(r"\.([A-Za-z_][A-Za-z0-9_]*)((?:\[[^\]]*\]|\{[^}]*\})*)")


def _parse(path: str) -> tuple[str, list[tuple[str, list[str]]]]:
    """A Foxglove message path as (topic, [(field, [index or filter, ...]), ...])."""
    if path.startswith('"'):
        end = path.index('"', 1)
        topic, rest = path[1:end], path[end + 1:]
    else:
        dot = path.find(".")
        topic, rest = (path, "") if dot < 0 else (path[:dot], path[dot:])
    steps, pos = [], 0
    while pos < len(rest):
        m = _STEP.match(rest, pos)
        assert m, f"{path}: cannot read the message path at {rest[pos:]!r}"
        steps.append((m.group(1), re.findall(r"\[[^\]]*\]|\{[^}]*\}", m.group(2))))
        pos = m.end()
    return topic, steps


def _field(obj: Any, name: str) -> Any:
    """Field ``name`` of a decoded message (JSON dict, ROS dataclass-like object, protobuf message);
    AssertionError naming the fields it has when it has no such field."""
    if isinstance(obj, dict):
        have = list(obj)
    elif hasattr(obj, "DESCRIPTOR"):
        have = list(obj.DESCRIPTOR.fields_by_name)
    else:
        have = [s for s in getattr(type(obj), "__slots__", ()) if not s.startswith("_")]
    assert name in have, f"no field {name!r} (it has {have})"
    return obj[name] if isinstance(obj, dict) else getattr(obj, name)


def _resolve(message: Any, steps: list[tuple[str, list[str]]]) -> tuple[Any, bool]:
    """The value a path's steps reach in ``message`` and whether it got to the end (an empty array on
    the way stops it: its fields cannot be seen in this message)."""
    value = message
    for name, subs in steps:
        value = _field(value, name)
        for sub in subs:
            if sub.startswith("{"):
                continue  # a filter keeps some items of the array: their fields are those of any item
            items = list(value)
            if not items:
                return value, False
            index = sub[1:-1]
            value = items[int(index) if re.fullmatch(r"-?\d+", index) else 0]
    return value, True


# -- the file and its shape ------------------------------------------------------------------------

def test_layout_is_a_foxglove_layout() -> None:
    path = layout_path()
    assert path.name == "foxglove_layout.json" and path.is_file()
    assert path.parent == (ROOT / "memlog" / "outputs")
    layout = _layout()
    assert set(layout) == {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"}
    assert isinstance(layout["globalVariables"], dict) and isinstance(layout["userNodes"], dict)
    assert layout["playbackConfig"]["speed"] > 0
    shown = list(_leaves(layout["layout"]))
    assert len(shown) == len(set(shown)), "a panel is placed twice"
    assert set(shown) == set(layout["configById"]), "every panel configured is placed, and only those"
    for pid, cfg in layout["configById"].items():
        assert re.fullmatch(r"[A-Za-z]+![A-Za-z0-9-]+", pid) and _panel_type(pid) in PANEL_TYPES, pid
        assert isinstance(cfg.get("foxglovePanelTitle"), str), pid
        if _panel_type(pid) == "Image":
            assert cfg["imageMode"]["imageTopic"] == LAYOUT_CAMERA
            # the current form: annotation topic -> settings
            assert all(s == {"visible": True} for s in cfg["imageMode"]["annotations"].values()), cfg
        if _panel_type(pid) in ("Plot", "StateTransitions"):
            for p in cfg["paths"]:
                assert p["timestampMethod"] in ("receiveTime", "headerStamp") and p["value"], p
                assert p.get("enabled", True) is True, p
    # every topic named is the camera or one of its memlog topics, and nothing else holds the camera's
    # text: replacing it (the documented retargeting) moves every panel to another camera
    text = layout_path().read_text(encoding="utf-8")
    assert all(t.startswith(LAYOUT_CAMERA) for _, _, t in _references(layout)), "a topic not of the camera"
    assert text.count(LAYOUT_CAMERA) == len(_references(layout))


def test_layout_has_the_panels_asked_for() -> None:
    """Image with the annotations, the three scores and the decision over time, the run's thresholds,
    and the match channel (best map frame, confidence)."""
    layout = _layout()
    scores, match = f"{LAYOUT_CAMERA}/memlog/scores", f"{LAYOUT_CAMERA}/memlog/match"
    refs = _references(layout)
    images = [(pid, t) for pid, k, t in refs if k == "image"]
    annotated = {pid for pid, k, t in refs if k == "annotations" and t == f"{LAYOUT_CAMERA}/memlog/annotations"}
    assert images and {pid for pid, _ in images} <= annotated
    plotted = {(_parse(t)[0], _parse(t)[1][0][0]) for pid, k, t in refs if k == "path" and _panel_type(pid) == "Plot"}
    assert {(scores, f) for f in ("ms", "ss", "es", "selected")} <= plotted
    assert {(match, "confidence"), (match, "matches")} <= plotted
    settings = [_parse(t) for pid, k, t in refs if _panel_type(pid) in ("Table", "RawMessages")]
    assert (scores, [("thresholds", [])]) in settings
    assert any(topic == match for topic, _ in settings)


# -- against what memlog writes -------------------------------------------------------------------

@dataclass
class Channel:
    schema: str
    encoding: str
    message: Any  # the first message, decoded


def _read(path: Path, topics: set[str]) -> dict[str, Channel]:
    """Every channel of an MCAP (schema name, message encoding) and the first message of ``topics``,
    decoded by the mcap project's decoders (ROS 1, ROS 2, protobuf) or as JSON."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoders
    from mcap_ros1.decoder import DecoderFactory as Ros1Decoders
    from mcap_ros2.decoder import DecoderFactory as Ros2Decoders

    factories = [Ros2Decoders(), Ros1Decoders(), ProtobufDecoders()]
    out: dict[str, Channel] = {}
    with path.open("rb") as f:
        reader = make_reader(f, decoder_factories=factories)
        summary = reader.get_summary()
        assert summary is not None
        for ch in summary.channels.values():
            schema = summary.schemas.get(ch.schema_id)
            out[ch.topic] = Channel(schema.name if schema else "", ch.message_encoding, None)
        for schema, ch, msg in reader.iter_messages(topics=sorted(topics & set(out))):
            if out[ch.topic].message is not None:
                continue
            if ch.message_encoding == "json":
                out[ch.topic].message = json.loads(msg.data)
                continue
            decoders = [d.decoder_for(ch.message_encoding, schema) for d in factories]
            decode = next((d for d in decoders if d is not None), None)
            assert decode is not None, f"{path}: no decoder for {ch.topic} ({ch.message_encoding})"
            out[ch.topic].message = decode(msg.data)
    return out


def _run_memlog(log: Path, camera: str, tmp: Path) -> dict[str, Channel]:
    """``memlog score`` (one frame of ``camera``) and ``memlog localize --annotate`` (against a thumbnail
    map of the same log) on ``log``; the channels of both outputs and the first message of each."""
    from memlog.cli.app import main
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.outputs.descriptor_table import write_descriptors

    scored, annotated = tmp / "scored.mcap", tmp / "query.mcap"
    assert main(["-q", "score", str(log), "-o", str(scored), "-t", camera, "--stride", "8"]) == 0
    table, _ = describe_log(log, make_describer("thumbnail"))
    write_descriptors(tmp / "map.parquet", table)
    assert main(["-q", "localize", str(tmp / "map.parquet"), str(log), "-o", str(tmp / "matches.parquet"),
                 "--annotate", str(annotated)]) == 0
    topics = {_parse(t)[0] for _, _, t in _references(_layout(camera))}
    channels = _read(annotated, topics)
    for topic, ch in _read(scored, topics).items():
        if channels.get(topic) is None or channels[topic].message is None:
            channels[topic] = ch
    return channels


@pytest.fixture(scope="module", params=list(FAMILIES))
def written(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
            ) -> tuple[dict[str, Any], dict[str, Channel]]:
    """(the layout for the fixture's camera, the channels memlog wrote for the fixture)."""
    name = str(request.param)
    camera = FAMILIES[name]
    return _layout(camera), _run_memlog(FIXTURES / name, camera, tmp_path_factory.mktemp(name.split(".")[0]))


def test_every_topic_is_one_memlog_writes(written: tuple[dict[str, Any], dict[str, Channel]]) -> None:
    layout, channels = written
    refs = _references(layout)
    camera = next(t for _, k, t in refs if k == "image")
    for pid, kind, text in refs:
        topic = text if kind != "path" else _parse(text)[0]
        assert topic in channels, f"{pid}: {topic} is not a topic of memlog's outputs ({sorted(channels)})"
        schema = channels[topic].schema
        if kind == "image":
            assert schema.rsplit("/", 1)[-1].rsplit(".", 1)[-1] in ("CompressedImage", "Image", "RawImage"), schema
        if kind == "annotations":
            assert schema.endswith("ImageAnnotations"), schema
    # and every channel memlog wrote for the camera is shown
    named = {text if kind != "path" else _parse(text)[0] for _, kind, text in refs}
    mine = {t for t in channels if t.startswith(f"{camera}/memlog/")}
    assert mine and mine <= named, f"not in the layout: {sorted(mine - named)}"


def test_every_message_path_resolves(written: tuple[dict[str, Any], dict[str, Channel]]) -> None:
    layout, channels = written
    for pid, kind, text in _references(layout):
        if kind != "path":
            continue
        topic, steps = _parse(text)
        message = channels[topic].message
        assert message is not None, f"{pid}: {topic} has no message to check {text} against"
        assert steps or _panel_type(pid) in ("RawMessages", "Table"), f"{pid}: {text} names no field"
        try:
            value, complete = _resolve(message, steps)
        except AssertionError as exc:
            raise AssertionError(f"{pid}: {text} ({channels[topic].schema}, {channels[topic].encoding}): {exc}")
        # a plotted value is a number (null in JSON, NaN in ROS: not computed, a gap in the plot)
        if _panel_type(pid) == "Plot" and complete:
            assert value is None or isinstance(value, (bool, int, float)), f"{pid}: {text} is not a number: {value!r}"
        if _panel_type(pid) == "StateTransitions" and complete:
            assert value is None or isinstance(value, (bool, int, str)), f"{pid}: {text} is not a state: {value!r}"


# -- package data --------------------------------------------------------------------------------

def test_the_installed_package_finds_the_layout(tmp_path: Path) -> None:
    """A wheel built from the tree (pyproject's package-data) carries the layout; installed, its own
    ``layout_path()`` names it. Built from a copy, so the tree gets no build/ or egg-info."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    shutil.copytree(ROOT / "memlog", src / "memlog", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    built = subprocess.run([*pip, "wheel", "--no-deps", "-w", str(tmp_path / "dist"), str(src)],
                           check=False, capture_output=True, text=True, timeout=600)
    assert built.returncode == 0, built.stderr[-3000:]
    wheel = next((tmp_path / "dist").glob("memlog-*.whl"))
    site = tmp_path / "site"
    installed = subprocess.run([*pip, "install", "--no-deps", "--no-index", "--target", str(site), str(wheel)],
                               check=False, capture_output=True, text=True, timeout=600)
    assert installed.returncode == 0, installed.stderr[-3000:]
    # -S: no site-packages, so neither the tree's editable install nor anything else can answer
    probe = ("import sys; sys.path.insert(0, sys.argv[1]); import json, memlog; "
             "from memlog.outputs.layout import layout_path; p = layout_path(); "
             "print(json.dumps([memlog.__file__, str(p), json.loads(p.read_text())]))")
    run = subprocess.run([sys.executable, "-S", "-c", probe, str(site)], check=False, capture_output=True, text=True,
                         cwd=tmp_path, timeout=120)
    assert run.returncode == 0, run.stderr
    module, found, content = json.loads(run.stdout)
    assert Path(module).resolve().is_relative_to(site.resolve())
    assert Path(found).resolve() == (site / "memlog" / "outputs" / "foxglove_layout.json").resolve()
    assert content == json.loads(layout_path().read_text(encoding="utf-8"))

#!/usr/bin/env python3
"""Descriptor choices measured at camera resolution on Stromovka, with Nordland beside it (issue 31).

What it measures: R@1, R@5 and AUC-PR (``benchmarks.matcher_defaults.metrics`` on the matcher's
``confidence``) of ``memlog.matching.match_tables`` — the drive matcher ``memlog
localize`` and ``memlog evaluate`` call — for three matchings: single frames
(``SequenceConfig(length=0, rerank=False)``), sequences (``SequenceConfig(rerank=False)``) and
sequences + patch re-rank (``SequenceConfig()``, the default), for these choices of the global
descriptor (DINOv2 ViT-S/14, 224 x 224 input):

* input: stretched (memlog's default) or letterboxed;
* pooling of the final tokens: GeM p = 1, 2, 3 (default), 4; CLS; mean;
* middle layers: GeM (p = 3) of the tokens of block 5, 7, 9; concatenations of L2-normalised
  GeM descriptors of several layers (L2-normalised again);
* multi-scale: the whole frame plus its centred crop of 75 % or of 60 % (the registered
  ``dinov2-gem-ms``), L2-normalised descriptors summed (as ``DinoV2Describer(scales=...)``);
* PCA-whitening fitted on the map's descriptors and applied to both drives: none, 16, 32, 50
  dimensions, memlog's default rule (``whitening_dim``: ``min(512, dim, n // 2)``, 50 on 101
  frames) and, beyond the rule, ``n - 1`` = 100.

Every descriptor choice other than the whitening rows is whitened by the default rule. Each
table's rows (frame index, log time, stamps, positions, moving index: what the matcher's
coordinates, runs and stops are made from) are memlog's own ``describe_log`` output for the
default descriptor; only the descriptors are swapped (same rows, same order). The re-rank's patch
features are the same for every choice: block-7 tokens pooled to 8 x 8 (``describe_log``'s), a
``PatchPCA`` fitted on the map's and applied to both. The variants are pooled from the network's
outputs directly: each frame is decoded once per run, each input (stretched, letterboxed, each
centred crop) goes through the network once with every output it needs (final tokens and blocks
5, 7, 9), and the tokens are cached per (log, input, output) in ``--cache`` (float32 ``.npy``).
The pooled default is checked against ``describe_log``'s descriptors.

Beside it, Nordland (summer map, winter query, 64 x 32 frames, 800 places, single frames and
sequences; no re-rank): the thumbnail (what ``--descriptor auto`` chooses at this size,
``memlog.descriptors.auto.choose_descriptor``), ``dinov2-gem`` (stretch, GeM p = 3) and the
best Stromovka choice (by sequences + re-rank R@1, then AUC-PR; the best other than the default
when the default wins), each whitened as above (default rule: 384 dimensions on 800 frames).

Data (``../shared/data``): ``stromovka_autumn.mcap`` (map, every frame) /
``stromovka_winter.mcap`` (query), 1024 x 384, 101 places, truth ``stromovka_truth.json``
(``matches``: the true map frames of each query frame); ``nordland_dev_summer.mcap`` /
``nordland_dev_winter.mcap``, truth ``nordland_dev_truth.json``.

    python benchmarks/descriptor_choices.py        # two Markdown tables (about 5-15 min on 2 cores)

Progress goes to stderr, the tables to stdout.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.matcher_defaults import PAIRS, SHARED, metrics

#: the matchings compared (name -> SequenceConfig arguments)
MATCHINGS: dict[str, dict[str, Any]] = {
    "single": {"length": 0, "rerank": False},
    "sequences": {"rerank": False},
    "seq + re-rank": {},
}
FINAL = "final"  # the final LayerNorm output; middle blocks are named by their number
BLOCKS = (5, 7, 9)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- network outputs


class Tokens:
    """Backbone tokens ``[N, 257, 384]`` of a log's frames (rows of its describe_log table), per
    (input, output), computed once and cached as ``.npy`` in ``cache``. Inputs: ``"stretch"``,
    ``"letterbox"`` (with its content-patch mask) and ``"crop0.75"``-style centred crops
    (stretched). Frames are decoded once per run and kept in memory."""

    def __init__(self, log_path: Path, frame_index: np.ndarray, cache: Path, session: Any,
                 all_blocks: bool = False) -> None:
        self.log_path, self.frame_index, self.cache, self.session = log_path, frame_index, cache, session
        self.all_blocks = all_blocks  # the stretched pass keeps blocks 5, 7, 9 too (one pass for all)
        st = log_path.stat()
        self.key = f"{log_path.stem}-{st.st_size}-{int(st.st_mtime)}"
        self._images: list[np.ndarray] | None = None
        self._mem: dict[tuple[str, str], np.ndarray] = {}

    def images(self) -> list[np.ndarray]:
        """The frames of ``frame_index`` (the first camera topic, as describe_log reads it), decoded."""
        if self._images is None:
            from memlog.errors import ImageDecodeError
            from memlog.io.base import FrameWindow
            from memlog.io.open import open_log

            with open_log(self.log_path) as reader:
                cams = reader.check_camera_topics(None)[:1]
                w = FrameWindow(tuple(cams))
                by_index: dict[int, np.ndarray] = {}
                for f in reader.frames(w.topics, w.start_ns, w.end_ns, w.stride):
                    try:
                        by_index[f.index] = f.decode_bgr()
                    except ImageDecodeError:  # describe_log left it out too (frame_index has it not)
                        pass
            self._images = [by_index[int(i)] for i in self.frame_index]
        return self._images

    def _path(self, inp: str, out: str) -> Path:
        return self.cache / f"{self.key}-{inp}-{out}.npy"

    def mask(self) -> np.ndarray:
        """Letterbox content-patch mask ``[N, 256]``."""
        from memlog.descriptors.dinov2 import preprocess

        return np.concatenate([preprocess(self.images()[a:a + 16], "letterbox")[1]
                               for a in range(0, len(self.frame_index), 16)])

    def get(self, inp: str, out: str) -> np.ndarray:
        if (inp, out) in self._mem:
            return self._mem[(inp, out)]
        p = self._path(inp, out)
        if not p.is_file():
            self._compute(inp, [FINAL, *BLOCKS] if inp == "stretch" and self.all_blocks else [FINAL])
        if not p.is_file():
            self._compute(inp, [out])
        arr = np.load(p, mmap_mode="r")
        if arr.shape[0] != len(self.frame_index):
            raise SystemExit(f"{p}: {arr.shape[0]} rows for {len(self.frame_index)} frames; delete the cache")
        self._mem[(inp, out)] = arr
        return arr

    def _compute(self, inp: str, outs: list[Any]) -> None:
        from memlog.descriptors.dinov2 import centre_crop, preprocess
        from memlog.models.dinov2 import N_TOKENS, TOKENS_OUTPUT, WIDTH, layer_output

        names = [TOKENS_OUTPUT if o == FINAL else layer_output(int(o)) for o in outs]
        n = len(self.frame_index)
        tmp = {o: self._path(inp, str(o)).with_suffix(".part.npy") for o in outs}
        arrs = {o: np.lib.format.open_memmap(tmp[o], mode="w+", dtype=np.float32, shape=(n, N_TOKENS, WIDTH))
                for o in outs}
        imgs = self.images()
        t0 = time.perf_counter()
        for a in range(0, n, 16):
            group = imgs[a:a + 16]
            if inp.startswith("crop"):
                x, _ = preprocess([centre_crop(im, float(inp[4:])) for im in group], "stretch")
            else:
                x, _ = preprocess(group, inp)
            res = self.session.run(names, {"input_image": x})
            for o, r in zip(outs, res):
                arrs[o][a:a + len(group)] = r
        for o in outs:
            arrs[o].flush()
            del arrs[o]
            tmp[o].replace(self._path(inp, str(o)))
        log(f"  {self.log_path.name}: {inp} -> {', '.join(map(str, outs))}: {n} frames, {time.perf_counter() - t0:.0f} s")


# --------------------------------------------------------------------------- descriptor choices


def _gem(t: np.ndarray, p: float, mask: np.ndarray | None = None) -> np.ndarray:
    from memlog.descriptors.dinov2 import pool_tokens

    return np.concatenate([pool_tokens(t[a:a + 64], "gem", p, None if mask is None else mask[a:a + 64])
                           for a in range(0, len(t), 64)])


def _pool(t: np.ndarray, pooling: str) -> np.ndarray:
    from memlog.descriptors.dinov2 import pool_tokens

    return np.concatenate([pool_tokens(t[a:a + 64], pooling) for a in range(0, len(t), 64)])


def _l2(x: np.ndarray) -> np.ndarray:
    from memlog.descriptors.base import l2_normalize

    return l2_normalize(x)


@dataclass(frozen=True)
class Choice:
    """A descriptor choice: ``raw(tokens)`` gives the unwhitened descriptors ``[N, d]``; ``whiten``
    is ``"rule"`` (memlog's default), ``None`` (none), an int (at most that many dimensions, the
    rule's cap) or ``"n-1"``."""

    group: str
    name: str
    raw: Callable[[Tokens], np.ndarray]
    whiten: Any = "rule"
    params: tuple[tuple[str, Any], ...] = ()


def _ms(tk: Tokens, crop: float) -> np.ndarray:
    return _l2(_gem(tk.get("stretch", FINAL), 3.0) + _gem(tk.get(f"crop{crop}", FINAL), 3.0))


def _concat(tk: Tokens, layers: tuple[Any, ...]) -> np.ndarray:
    return _l2(np.concatenate([_gem(tk.get("stretch", layer), 3.0) for layer in layers], axis=1))


def default_raw(tk: Tokens) -> np.ndarray:
    return _gem(tk.get("stretch", FINAL), 3.0)


CHOICES: list[Choice] = [
    Choice("input", "stretch, GeM p=3 (default)", default_raw),
    Choice("input", "letterbox, GeM p=3", lambda tk: _gem(tk.get("letterbox", FINAL), 3.0, tk.mask()),
           params=(("resize", "letterbox"),)),
    Choice("pooling", "GeM p=1", lambda tk: _gem(tk.get("stretch", FINAL), 1.0), params=(("gem_p", 1.0),)),
    Choice("pooling", "GeM p=2", lambda tk: _gem(tk.get("stretch", FINAL), 2.0), params=(("gem_p", 2.0),)),
    Choice("pooling", "GeM p=4", lambda tk: _gem(tk.get("stretch", FINAL), 4.0), params=(("gem_p", 4.0),)),
    Choice("pooling", "CLS", lambda tk: _pool(tk.get("stretch", FINAL), "cls"), params=(("pooling", "cls"),)),
    Choice("pooling", "mean", lambda tk: _pool(tk.get("stretch", FINAL), "mean"), params=(("pooling", "mean"),)),
    *[Choice("layer", f"GeM block {b}", (lambda tk, b=b: _gem(tk.get("stretch", b), 3.0)), params=(("layer", b),))
      for b in BLOCKS],
    Choice("layer", "GeM block 7 ++ final", lambda tk: _concat(tk, (7, FINAL)), params=(("layers", "7+final"),)),
    Choice("layer", "GeM block 9 ++ final", lambda tk: _concat(tk, (9, FINAL)), params=(("layers", "9+final"),)),
    Choice("layer", "GeM blocks 5 ++ 7 ++ 9 ++ final", lambda tk: _concat(tk, (5, 7, 9, FINAL)),
           params=(("layers", "5+7+9+final"),)),
    Choice("multi-scale", "scales 1.0 + 0.75", lambda tk: _ms(tk, 0.75), params=(("scales", "1.0,0.75"),)),
    Choice("multi-scale", "scales 1.0 + 0.6 (dinov2-gem-ms)", lambda tk: _ms(tk, 0.6), params=(("scales", "1.0,0.6"),)),
    Choice("whitening", "none", default_raw, whiten=None),
    Choice("whitening", "16", default_raw, whiten=16),
    Choice("whitening", "32", default_raw, whiten=32),
    Choice("whitening", "50", default_raw, whiten=50),
    Choice("whitening", "default rule", default_raw),
    Choice("whitening", "n - 1 (beyond the rule)", default_raw, whiten="n-1"),
]


def fit_whiten(map_raw: np.ndarray, how: Any) -> Any:
    """The whitening ``how`` fitted on the map's raw descriptors (None: no whitening)."""
    from memlog.descriptors.whitening import DEFAULT_EPS, Whitening, fit_whitening

    if how is None:
        return None
    if how == "rule":
        return fit_whitening(map_raw, source="map")
    if isinstance(how, int):
        return fit_whitening(map_raw, max_dim=how, source="map")
    # n - 1 dimensions: fit_whitening's arithmetic without the rule's n // 2 cap
    x = np.asarray(map_raw, dtype=np.float64)
    k = min(x.shape[1], len(x) - 1)
    mean = x.mean(axis=0)
    cov = x.T @ x / len(x) - np.outer(mean, mean)
    vals, vecs = np.linalg.eigh((cov + cov.T) / 2.0)
    order = np.argsort(vals)[::-1]
    vals, vecs = np.clip(vals[order], 0.0, None), vecs[:, order]
    scale = 1.0 / np.sqrt(vals[:k] + DEFAULT_EPS * max(float(vals[0]), 1e-12))
    return Whitening(mean.astype(np.float32), (vecs[:, :k] * scale).astype(np.float32), len(x), DEFAULT_EPS, "map")


def swap(ref: Any, query: Any, ref_raw: np.ndarray, q_raw: np.ndarray, how: Any, kind: str,
         params: dict[str, Any]) -> tuple[Any, Any]:
    """The two tables with these descriptors (whitened by ``how`` fitted on the map's), rows kept."""
    from memlog.descriptors.base import DescriptorMeta

    w = fit_whiten(ref_raw, how)
    r, q = (ref_raw, q_raw) if w is None else (w.apply(ref_raw), w.apply(q_raw))
    meta = DescriptorMeta(kind, "bench", int(r.shape[1]), ref.meta.model_sha256, dict(params),
                          whitening=None if w is None else w.sha256)
    return (replace(ref, descriptors=r, meta=meta, whitening=w),
            replace(query, descriptors=q, meta=meta, whitening=None))


def evaluate(ref: Any, query: Any, truth: list[set[int]], matchings: list[str]) -> dict[str, dict[str, float]]:
    from memlog.matching import SequenceConfig, match_tables

    out = {}
    sets = [truth[int(f)] for f in query.frame_index]
    for name in matchings:
        res = match_tables(query, ref, SequenceConfig(**MATCHINGS[name]), k=10)
        if name == "seq + re-rank" and "off" in res.info.get("rerank", {}):
            raise SystemExit(f"the re-rank did not run: {res.info['rerank']}")
        frames = np.where(res.indices >= 0, ref.frame_index[np.maximum(res.indices, 0)], -1)
        out[name] = metrics(frames, res.confidence, sets)
    return out


def cells(m: dict[str, dict[str, float]], names: list[str]) -> str:
    return " | ".join(f"{m[n]['r1']:.3f} | {m[n]['r5']:.3f} | {m[n]['auc']:.3f}" for n in names)


def header(first: str, names: list[str]) -> str:
    cols = " | ".join(f"{n} R@1 | {n} R@5 | {n} AUC" for n in names)
    return f"| {first} | dim | {cols} |\n|" + "---|" * (2 + first.count("|") + 3 * len(names))


# --------------------------------------------------------------------------- the pairs


def load_truth(pair: str) -> list[set[int]]:
    return [set(m) for m in json.loads((SHARED / PAIRS[pair][2]).read_text())["matches"]]


def stromovka(cache: Path, session: Any) -> tuple[Choice, Choice | None]:
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.patches import PatchPCA
    from memlog.descriptors.registry import make_describer

    ref_log, q_log = SHARED / PAIRS["stromovka"][0], SHARED / PAIRS["stromovka"][1]
    truth = load_truth("stromovka")
    describer = make_describer("dinov2-gem")
    t0 = time.perf_counter()
    ref, _ = describe_log(ref_log, describer, patches=True)  # raw descriptors and raw patches
    query, _ = describe_log(q_log, describer, patches=True)
    log(f"stromovka: describe_log of both drives ({len(ref)} + {len(query)} frames), {time.perf_counter() - t0:.0f} s")
    pca = PatchPCA.fit(ref.patches)  # the map's raw pooled patches (float16, as memlog map fits them)
    ref = replace(ref, patches=pca.apply(ref.patches), patch_pca=pca)
    query = replace(query, patches=pca.apply(query.patches), patch_pca=pca)
    tk_ref = Tokens(ref_log, ref.frame_index, cache, session, all_blocks=True)
    tk_q = Tokens(q_log, query.frame_index, cache, session, all_blocks=True)
    # the pooled default is memlog's describer's output
    diff = max(float(np.abs(default_raw(tk_ref) - ref.descriptors).max()),
               float(np.abs(default_raw(tk_q) - query.descriptors).max()))
    if diff > 1e-4:
        raise SystemExit(f"pooled default differs from describe_log's descriptors by {diff:.2e}")

    names = list(MATCHINGS)
    print(f"Stromovka: autumn map ({len(ref)} frames, every frame) / winter query ({len(query)} frames), "
          f"1024x384; whitening fitted on the map (default rule: {whiten_dim_note(len(ref))}); re-rank patches: "
          f"block 7 pooled 8x8, PCA {pca.dim}-d fitted on the map\n")
    print(header("choice | descriptor", names))
    results: list[tuple[Choice, dict[str, dict[str, float]]]] = []
    same: set[str] = set()  # choices whose descriptors are the default's (whitening 50 = the rule on 101 frames)
    default_desc: np.ndarray | None = None
    for c in CHOICES:
        r, q = swap(ref, query, c.raw(tk_ref), c.raw(tk_q), c.whiten, "dinov2-gem", dict(c.params))
        if default_desc is None:
            default_desc = r.descriptors
        elif r.descriptors.shape == default_desc.shape and np.array_equal(r.descriptors, default_desc):
            same.add(c.name)
        m = evaluate(r, q, truth, names)
        results.append((c, m))
        print(f"| {c.group} | {c.name} | {r.descriptors.shape[1]} | {cells(m, names)} |", flush=True)
    print(f"\n(pooled default against describe_log's descriptors: max |diff| {diff:.1e})")

    def key(cm: tuple[Choice, dict[str, dict[str, float]]]) -> tuple[float, float]:
        return (round(cm[1]["seq + re-rank"]["r1"], 6), round(cm[1]["seq + re-rank"]["auc"], 6))

    ranked = sorted(results, key=key, reverse=True)
    best = ranked[0][0]
    other = next(c for c, _ in ranked if c is not CHOICES[0] and c.name not in same)
    if best.name in same:
        best = CHOICES[0]
    return best, (other if other is not best else None)


def whiten_dim_note(n: int) -> str:
    from memlog.descriptors.whitening import whitening_dim

    return f"{whitening_dim(n, 384)} dims on {n} frames"


def nordland(cache: Path, session: Any, best: Choice, runner_up: Choice | None) -> None:
    from memlog.descriptors.auto import choose_descriptor, probe_frame_size
    from memlog.descriptors.extract import describe_log
    from memlog.descriptors.registry import make_describer
    from memlog.io.open import open_log

    ref_log, q_log = SHARED / PAIRS["nordland"][0], SHARED / PAIRS["nordland"][1]
    truth = load_truth("nordland")
    with open_log(ref_log) as reader:
        topic = reader.check_camera_topics(None)[0]
        size = probe_frame_size(reader, topic)
    auto = choose_descriptor("auto", size)
    thumb = make_describer("thumbnail")
    t0 = time.perf_counter()
    ref, _ = describe_log(ref_log, thumb)  # thumbnails give no patches: no re-rank on Nordland
    query, _ = describe_log(q_log, thumb)
    log(f"nordland: describe_log of both drives ({len(ref)} + {len(query)} frames), {time.perf_counter() - t0:.0f} s")
    tk_ref = Tokens(ref_log, ref.frame_index, cache, session)
    tk_q = Tokens(q_log, query.frame_index, cache, session)
    names = ["single", "sequences"]
    rows: list[tuple[str, Any, Any, Any, str, dict[str, Any]]] = [
        (f"thumbnail (auto: {auto.describe()})", ref.descriptors, query.descriptors, "rule", "thumbnail", {}),
        ("dinov2-gem (stretch, GeM p=3)", None, None, "rule", "dinov2-gem", {}),
    ]
    extra = [best] if best is not CHOICES[0] else []
    if runner_up is not None:
        extra.append(runner_up)
    print(f"\nNordland: summer map / winter query ({len(ref)} frames each, {size[0]}x{size[1]}), "
          "single frames and sequences (thumbnails give no patch features: no re-rank)\n")
    print(header("descriptor", names))
    specs = rows + [(f"{c.name} ({c.group}; Stromovka {'best' if c is best else 'best other than the default'})",
                     c, None, c.whiten, "dinov2-gem", dict(c.params)) for c in extra]
    for label, r_raw, q_raw, how, kind, params in specs:
        if r_raw is None:
            r_raw, q_raw = default_raw(tk_ref), default_raw(tk_q)
        elif isinstance(r_raw, Choice):
            r_raw, q_raw = r_raw.raw(tk_ref), r_raw.raw(tk_q)
        r, q = swap(ref, query, r_raw, q_raw, how, kind, params)
        m = evaluate(r, q, truth, names)
        print(f"| {label} | {r.descriptors.shape[1]} | {cells(m, names)} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/memlog-descriptor-choices"),
                    help="where the network's tokens are cached (float32 .npy, about 1 GB)")
    a = ap.parse_args()
    a.cache.mkdir(parents=True, exist_ok=True)
    from memlog.models.dinov2 import dinov2_session

    t0 = time.perf_counter()
    session = dinov2_session(None)
    best, runner_up = stromovka(a.cache, session)
    nordland(a.cache, session, best, runner_up)
    log(f"done in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Entropy map E and score ES: the fast exact implementation against scikit-image."""

from __future__ import annotations

import math

import cv2
import numpy as np
import numpy.typing as npt
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from skimage.filters.rank import entropy as sk_entropy
from skimage.morphology import disk

from memlog.errors import ScoringError
from memlog.runtime import Runtime, current, use
from memlog.scoring import entropy as entropy_mod
from memlog.scoring.entropy import Entropy, disk_footprint, entropy_kernel, entropy_map, entropy_score
from tests.conftest import shared, skip_or_fail

TOL = 1e-9


@pytest.fixture(params=["c", "numpy"])
def kernel(request: pytest.FixtureRequest) -> str:
    """Both implementations: the compiled kernel (built by ``pip install``; CI has a C compiler, so
    there it must be built) and the numpy one."""
    if request.param == "c" and entropy_mod._compiled() is None:
        skip_or_fail("memlog's compiled entropy kernel is not built (no C compiler when memlog was installed)")
    return str(request.param)


def _reference(gray: npt.NDArray[np.uint8], radius: int = 5) -> npt.NDArray[np.float64]:
    return np.asarray(sk_entropy(gray, disk(radius)), dtype=np.float64)


def _nordland_gray(index: int = 350) -> npt.NDArray[np.uint8]:
    """One real frame of the Nordland log, as the spec prepares it: BGR, 1135 INTER_LINEAR, grey."""
    with open(shared("nordland_dev_summer.mcap"), "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for i, (_, _, _, msg) in enumerate(reader.iter_decoded_messages(topics=["/camera/image_raw/compressed"])):
            if i == index:
                bgr = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_COLOR)
                break
        else:
            pytest.fail(f"nordland_dev_summer.mcap has fewer than {index + 1} frames")
    assert bgr is not None and bgr.shape == (32, 64, 3)
    frame = cv2.resize(bgr, (1135, 1135), interpolation=cv2.INTER_LINEAR)
    return np.asarray(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY), dtype=np.uint8)


@pytest.mark.parametrize("radius", range(0, 11))
def test_footprint_is_skimage_disk(radius: int) -> None:
    assert np.array_equal(disk_footprint(radius), disk(radius))


def test_random_image_matches_skimage(kernel: str) -> None:
    gray = np.random.default_rng(0).integers(0, 256, (301, 419), dtype=np.uint8)
    e = entropy_map(gray, kernel=kernel)
    assert e.dtype == np.float64 and e.shape == gray.shape
    assert np.abs(e - _reference(gray)).max() <= TOL


def test_real_frame_1135_matches_skimage(kernel: str) -> None:
    gray = _nordland_gray()
    assert gray.shape == (1135, 1135) and gray.std() > 5  # a real, textured frame
    e = entropy_map(gray, kernel=kernel)
    ref = _reference(gray)
    assert np.abs(e - ref).max() <= TOL
    assert 0.0 < e.mean() < 8.0


@pytest.mark.parametrize("shape", [(37, 53), (53, 37), (1, 1), (1, 9), (9, 1), (4, 4), (11, 11), (12, 131)])
@pytest.mark.parametrize("radius", [1, 2, 5, 8])
def test_odd_sizes_and_borders(shape: tuple[int, int], radius: int, kernel: str) -> None:
    """Edge pixels count only their in-image neighbours, like scikit-image."""
    rng = np.random.default_rng(shape[0] * 1000 + shape[1] * 10 + radius)
    for levels in (256, 3):  # many values; few values (ties in every histogram)
        gray = rng.integers(0, levels, shape, dtype=np.uint8)
        assert np.abs(entropy_map(gray, radius, kernel=kernel) - _reference(gray, radius)).max() <= TOL


def test_large_radius_uses_wide_counts(kernel: str) -> None:
    """disk(10) has 317 pixels: counts no longer fit uint8."""
    gray = np.random.default_rng(11).integers(0, 256, (45, 70), dtype=np.uint8)
    assert np.abs(entropy_map(gray, 10, kernel=kernel) - _reference(gray, 10)).max() <= TOL


def test_border_pixel_by_hand() -> None:
    """Corner of a 2-value image: the histogram holds the 26 in-image disk pixels only."""
    gray = np.zeros((20, 20), np.uint8)
    gray[0, 0] = 1
    n = int(disk(5)[5:, 5:].sum())  # quarter disk including the axes
    assert n == 26
    p = np.array([1, n - 1]) / n
    expected = float(-(p * np.log2(p)).sum())
    assert entropy_map(gray)[0, 0] == pytest.approx(expected, abs=1e-12)


def test_constant_image_is_zero() -> None:
    gray = np.full((64, 80), 137, np.uint8)
    e = entropy_map(gray)
    assert not e.any()
    assert entropy_score(e) == 0.0  # a textureless wall


def test_entropy_range() -> None:
    gray = np.random.default_rng(3).integers(0, 256, (128, 128), dtype=np.uint8)
    e = entropy_map(gray)
    assert e.min() >= 0.0 and e.max() <= math.log2(81) + 1e-12


def _expected_plugin_entropy(n: int, bins: int = 256) -> float:
    """E[H] of the histogram of n uniform draws over ``bins`` values (binomial bin counts)."""
    k = np.arange(n + 1)
    logpmf = np.array(
        [math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) for i in k]
    ) + k * math.log(1 / bins) + (n - k) * math.log(1 - 1 / bins)
    f = np.zeros(n + 1)
    f[1:] = k[1:] * np.log2(k[1:])
    return math.log2(n) - bins * float((np.exp(logpmf) * f).sum()) / n


def test_noise_score_matches_its_expectation() -> None:
    """ES of uniform noise is the mean of E[H(n)] over the pixels (n in-image neighbours)."""
    size = 400
    gray = np.random.default_rng(7).integers(0, 256, (size, size), dtype=np.uint8)
    es = entropy_score(entropy_map(gray))
    ones = np.ones((size, size), np.float32)
    nmap = np.rint(cv2.filter2D(ones, -1, disk(5).astype(np.float32), borderType=cv2.BORDER_CONSTANT)).astype(int)
    vals, counts = np.unique(nmap, return_counts=True)
    expected = sum(c * _expected_plugin_entropy(int(v)) for v, c in zip(vals, counts)) / (size * size * 8)
    assert 0.7 < expected < 0.8
    assert es == pytest.approx(expected, abs=2e-3)


def test_score_masks_dynamic_pixels() -> None:
    gray = np.random.default_rng(1).integers(0, 256, (60, 90), dtype=np.uint8)
    e = entropy_map(gray)
    s = np.ones(e.shape, np.uint8)
    s[:, :45] = 0
    assert entropy_score(e, s) == pytest.approx(e[:, 45:].sum() / (60 * 90 * 8), rel=1e-12)
    assert entropy_score(e, np.zeros(e.shape, np.uint8)) == 0.0
    assert entropy_score(e, s.astype(bool)) == entropy_score(e, s)


def test_workers_give_the_same_map(kernel: str) -> None:
    gray = np.random.default_rng(5).integers(0, 256, (260, 300), dtype=np.uint8)
    one = entropy_map(gray, kernel=kernel)
    assert np.abs(entropy_map(gray, workers=2, kernel=kernel) - one).max() <= 1e-12
    assert np.abs(entropy_map(gray, workers=3, kernel=kernel) - one).max() <= 1e-12


def test_the_two_kernels_agree_on_a_camera_frame(kernel: str) -> None:
    """The compiled kernel and the numpy one on a real 1135 x 1135 frame: the same map up to float
    rounding, so scores (and the frames a map keeps) do not depend on which one ran."""
    gray = _nordland_gray()
    other = "numpy" if kernel == "c" else "c"
    if other == "c" and entropy_mod._compiled() is None:
        skip_or_fail("memlog's compiled entropy kernel is not built")
    a, b = entropy_map(gray, kernel=kernel), entropy_map(gray, kernel=other)
    assert np.abs(a - b).max() <= 1e-12
    assert entropy_score(a) == pytest.approx(entropy_score(b), abs=1e-13)


def test_kernel_choice(monkeypatch: pytest.MonkeyPatch) -> None:
    """``auto`` takes the compiled kernel when it is built; the runtime context (the environment, for
    the command line and the API) can force numpy; asking for the compiled kernel without it is a
    clear error, not a silent fallback."""
    with use(current().replace(entropy_kernel="auto")):
        built = entropy_mod._compiled() is not None
        assert entropy_kernel() == ("c" if built else "numpy")
        assert entropy_kernel("numpy") == "numpy"
        with use(Runtime.from_environment({"MEMLOG_ENTROPY_KERNEL": "numpy"})):
            assert entropy_kernel() == "numpy" and Entropy(5).kernel == "numpy"
        with pytest.raises(ScoringError, match="MEMLOG_ENTROPY_KERNEL"):
            Runtime.from_environment({"MEMLOG_ENTROPY_KERNEL": "fortran"})
        with pytest.raises(ScoringError, match="kernel must be one of"):
            entropy_map(np.zeros((4, 4), np.uint8), kernel="gpu")
        monkeypatch.setattr(entropy_mod, "_compiled", lambda: None)
        assert entropy_kernel() == "numpy"
        with pytest.raises(ScoringError, match="C compiler"):
            entropy_map(np.zeros((4, 4), np.uint8), kernel="c")


def test_class_is_a_thin_wrapper() -> None:
    gray = np.random.default_rng(2).integers(0, 256, (40, 50), dtype=np.uint8)
    ent = Entropy(5)
    assert ent.radius == 5 and "radius=5" in repr(ent)
    assert np.array_equal(ent(gray), entropy_map(gray, 5))


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((10, 10, 3), np.uint8), "2-D"),
        (np.zeros((10,), np.uint8), "2-D"),
        (np.zeros((10, 10), np.float32), "uint8"),
        (np.zeros((10, 10), np.uint16), "uint8"),
        (np.zeros((0, 10), np.uint8), "empty"),
        ([[1, 2], [3, 4]], "numpy array"),
    ],
)
def test_shape_errors(bad: object, match: str) -> None:
    with pytest.raises(ScoringError, match=match):
        entropy_map(bad)  # type: ignore[arg-type]


def test_argument_errors() -> None:
    gray = np.zeros((10, 10), np.uint8)
    with pytest.raises(ScoringError, match="radius"):
        entropy_map(gray, -1)
    with pytest.raises(ScoringError, match="radius"):
        Entropy(2.5)  # type: ignore[arg-type]
    with pytest.raises(ScoringError, match="workers"):
        entropy_map(gray, workers=0)
    with pytest.raises(ScoringError, match="does not match"):
        entropy_score(np.zeros((10, 10)), np.ones((10, 11), np.uint8))
    with pytest.raises(ScoringError, match="2-D"):
        entropy_score(np.zeros((10, 10, 1)))

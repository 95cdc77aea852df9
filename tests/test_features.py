"""dhptam.features: the extractor interface, zero-copy hand-over, matching, torch-free installs."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import torch
from conftest import shared_path
from skimage import data

from dhptam import Config, _core, features
from dhptam.errors import FileError, InputError
from dhptam.features.superpoint import SuperPoint, SuperPointNet


def _camera(width: int = 240, height: int = 180) -> npt.NDArray[np.uint8]:
    return cv2.resize(data.camera(), (width, height), interpolation=cv2.INTER_AREA)


def _extractors() -> dict[str, features.Extractor]:
    torch.manual_seed(0)
    return {
        "orb": features.load("orb", max_keypoints=300),
        "sift": features.load("sift", max_keypoints=300),
        "r2d2": features.load(
            "r2d2", shared_path("models", "r2d2", "faster2d2_WASF_N16.pt"), device="cpu", max_keypoints=300
        ),
        # Random weights: the memory layout of the outputs does not depend on their values.
        "superpoint": SuperPoint(None, net=SuperPointNet(), device="cpu", max_keypoints=300),
    }


@pytest.fixture(scope="module")
def extracted() -> dict[str, tuple[features.Features, features.Features]]:
    image = _camera()
    shifted = np.roll(image, 3, axis=1)
    return {name: ex.extract(image, shifted) for name, ex in _extractors().items()}


@pytest.mark.parametrize("name", ["orb", "sift", "r2d2", "superpoint"])
def test_outputs_follow_the_contract(extracted: dict, name: str) -> None:
    widths = {"orb": 32, "sift": 128, "r2d2": 128, "superpoint": 256}
    for f in extracted[name]:
        n = len(f)
        assert 20 < n <= 300
        assert f.keypoints.dtype == np.float32 and f.keypoints.shape == (n, 2)
        assert f.scores.dtype == np.float32 and f.scores.shape == (n,)
        assert f.sigmas.dtype == np.float32 and f.sigmas.shape == (n,) and (f.sigmas >= 1.0).all()
        assert f.descriptors.shape == (n, widths[name])
        assert f.descriptors.dtype == (np.uint8 if name == "orb" else np.float32)
        assert f.binary == (name == "orb")
        assert (np.diff(f.scores) <= 0).all(), "best scores first"
        assert (
            (f.keypoints >= 0).all() and (f.keypoints[:, 0] <= 239).all() and (f.keypoints[:, 1] <= 179).all()
        )
        if name != "orb":
            np.testing.assert_allclose(np.linalg.norm(f.descriptors, axis=1), 1.0, atol=1e-5)
        # Sub-pixel: positions are not all on the integer grid.
        assert (np.abs(f.keypoints - np.round(f.keypoints)) > 1e-3).mean() > 0.2


@pytest.mark.parametrize("name", ["orb", "sift", "r2d2", "superpoint"])
def test_rust_reads_the_extractor_outputs_in_place(extracted: dict, name: str) -> None:
    left, _ = extracted[name]
    for array in (left.keypoints, left.scores, left.descriptors, left.sigmas):
        assert array.flags.c_contiguous
        assert _core._buffer_address(array) == array.__array_interface__["data"][0]
    assert _core._buffer_address(left.descriptors) == left.descriptors.__array_interface__["data"][0]
    # The check can fail: an array of another dtype is converted, so its address differs.
    as_f64 = left.keypoints.astype(np.float64)
    assert _core._buffer_address(as_f64) != as_f64.__array_interface__["data"][0]
    strided = np.asfortranarray(np.zeros((8, 2), np.float32))
    assert _core._buffer_address(strided) != strided.__array_interface__["data"][0]


def _reference_matches(
    q: npt.NDArray, t: npt.NDArray, max_distance: float, ratio: float, mutual: bool
) -> list[tuple[int, int]]:
    if q.dtype == np.uint8:
        d = np.unpackbits(q[:, None, :] ^ t[None, :, :], axis=2).sum(axis=2).astype(np.float64)
    else:
        d = np.linalg.norm(q[:, None, :].astype(np.float64) - t[None, :, :], axis=2)
    out = []
    for i in range(len(q)):
        order = np.argsort(d[i], kind="stable")
        j = int(order[0])
        second = d[i, order[1]] if len(order) > 1 else np.inf
        if d[i, j] > max_distance or (ratio < 1.0 and not d[i, j] < ratio * second):
            continue
        if mutual and int(np.argmin(d[:, j])) != i:
            continue
        out.append((i, j))
    return out


@pytest.mark.parametrize("name", ["orb", "sift", "r2d2", "superpoint"])
@pytest.mark.parametrize(("ratio", "mutual"), [(0.8, True), (1.0, False), (0.95, True)])
def test_match_equals_a_brute_force_reference(extracted: dict, name: str, ratio: float, mutual: bool) -> None:
    left, right = extracted[name]
    limit = 64.0 if name == "orb" else 0.9
    pairs, distances = features.match(left, right, ratio=ratio, mutual=mutual)
    expected = _reference_matches(left.descriptors, right.descriptors, limit, ratio, mutual)
    assert [tuple(p) for p in pairs.tolist()] == expected
    assert pairs.dtype == np.int64 and distances.dtype == np.float32
    if name != "orb":
        np.testing.assert_allclose(
            distances,
            np.linalg.norm(left.descriptors[pairs[:, 0]] - right.descriptors[pairs[:, 1]], axis=1),
            atol=1e-5,
        )
    # max_distance cuts.
    tight, tight_d = features.match(
        left, right, max_distance=float(np.median(distances)), ratio=ratio, mutual=mutual
    )
    assert len(tight) < len(pairs) and (tight_d <= np.median(distances)).all()


def test_matches_follow_the_shift_between_the_images(extracted: dict) -> None:
    # The right image is the left one rolled 3 px to the right: correct matches move by +3 px.
    # Measured fractions within 1 px: orb 0.86, sift 0.99, r2d2 (faster2d2) 0.87.
    for name in ("orb", "sift", "r2d2"):
        left, right = extracted[name]
        pairs, _ = features.match(left, right)
        shift = right.keypoints[pairs[:, 1]] - left.keypoints[pairs[:, 0]]
        good = np.linalg.norm(shift - [3.0, 0.0], axis=1) < 1.0
        assert len(pairs) > 100 and good.mean() > 0.75, (name, good.mean())


def test_empty_images_give_empty_features_that_match() -> None:
    flat = np.full((64, 80), 128, np.uint8)
    for name in ("orb", "sift"):
        left, right = features.load(name).extract(flat, flat)
        assert len(left) == 0 and left.descriptors.shape[1] in (32, 128)
        pairs, distances = features.match(left, right)
        assert pairs.shape == (0, 2) and distances.shape == (0,)


def test_bad_images_and_arguments_are_named() -> None:
    orb = features.load("orb")
    image = _camera()
    with pytest.raises(InputError, match=r"image_left.*uint8"):
        orb.extract(image.astype(np.float32), image)
    with pytest.raises(InputError, match=r"image_right.*size"):
        orb.extract(image, image[:100])
    with pytest.raises(InputError, match=r"image_left.*grayscale"):
        orb.extract(np.dstack([image] * 3), image)
    with pytest.raises(InputError, match=r"name.*superpoint, r2d2, orb, sift"):
        features.load("surf")
    with pytest.raises(InputError, match="max_keypoints"):
        features.load("sift", max_keypoints=0)
    with pytest.raises(InputError, match="weights: orb needs no weights"):
        features.load("orb", weights="x.pt")
    with pytest.raises(FileError, match=r"does-not-exist.pt"):
        features.load("r2d2", "/nowhere/does-not-exist.pt", device="cpu")
    with pytest.raises(InputError, match="device"):
        features.load("r2d2", shared_path("models", "r2d2", "faster2d2_WASF_N16.pt"), device="tpu")
    if not torch.cuda.is_available():
        with pytest.raises(InputError, match="CUDA is not available"):
            features.load("r2d2", shared_path("models", "r2d2", "faster2d2_WASF_N16.pt"), device="cuda")
    with pytest.raises(InputError, match="keypoints"):
        features.Features(np.zeros((3, 2)), np.zeros(3, np.float32), np.zeros((3, 8), np.float32))
    with pytest.raises(InputError, match="descriptors"):
        features.Features(np.zeros((3, 2), np.float32), np.zeros(3, np.float32), np.zeros((2, 8), np.float32))


def test_orb_sigmas_are_the_scale_factor_to_the_octave() -> None:
    extractor = features.load("orb", max_keypoints=500)
    image = _camera(480, 360)
    f = extractor.extract_one(image)
    # The octave of each keypoint straight from OpenCV, found again by position and score
    # (one corner may be detected at two levels).
    raw = cv2.ORB_create(nfeatures=500).detect(image, None)
    octave = {(*np.float32(k.pt).tolist(), float(np.float32(k.response))): k.octave for k in raw}
    found = zip(f.keypoints.tolist(), f.scores.tolist(), strict=True)
    expected = [1.2 ** octave[(x, y, r)] for (x, y), r in found]
    np.testing.assert_allclose(f.sigmas, expected, rtol=1e-6)
    assert len(np.unique(f.sigmas)) >= 3, "keypoints from several pyramid levels"


def test_sift_r2d2_and_superpoint_sigmas_follow_their_detection_scale(extracted: dict) -> None:
    for f in extracted["sift"]:
        exponent = np.log2(f.sigmas)
        np.testing.assert_allclose(exponent, np.round(exponent), atol=1e-6)
    # The 240×180 test image runs R2D2 at scales 1 and 0.75: σ 1 and 4/3 px, both present.
    for f in extracted["r2d2"]:
        np.testing.assert_allclose(np.unique(f.sigmas), [1.0, 4.0 / 3.0], rtol=1e-3)
    for f in extracted["superpoint"]:
        assert (f.sigmas == 1.0).all()


def test_bad_sigmas_are_refused_naming_the_field() -> None:
    kp, sc, de = np.zeros((3, 2), np.float32), np.zeros(3, np.float32), np.zeros((3, 8), np.float32)
    assert (features.Features(kp, sc, de).sigmas == 1.0).all()
    ok = features.Features(kp, sc, de, np.array([1.0, 1.2, 1.44], np.float32))
    assert ok.sigmas.tolist() == pytest.approx([1.0, 1.2, 1.44])
    for bad in (
        np.ones(2, np.float32),  # wrong length
        np.ones((3, 1), np.float32),  # wrong shape
        np.ones(3, np.float64),  # wrong dtype
        np.array([1.0, 0.0, 1.0], np.float32),
        np.array([1.0, -2.0, 1.0], np.float32),
        np.array([1.0, np.nan, 1.0], np.float32),
        np.array([1.0, np.inf, 1.0], np.float32),
        [1.0, 1.0, 1.0],
    ):
        with pytest.raises(InputError, match="sigmas") as info:
            features.Features(kp, sc, de, bad)  # type: ignore[arg-type]
        assert info.value.field == "sigmas"
    with pytest.raises(InputError, match="C-contiguous"):
        features.Features(kp, sc, de, np.ones(6, np.float32)[::2])


def test_device_auto_and_threads() -> None:
    path = shared_path("models", "r2d2", "faster2d2_WASF_N16.pt")
    before = torch.get_num_threads()
    try:
        extractor = features.load("r2d2", path, threads=1)
        assert extractor.device.type == ("cuda" if torch.cuda.is_available() else "cpu")  # type: ignore[attr-defined]
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_config_section_builds_the_extractor(monkeypatch: pytest.MonkeyPatch) -> None:
    extractor = features.from_config(Config.from_toml('[features]\nextractor = "orb"\nmax_keypoints = 77'))
    assert extractor.name == "orb" and extractor.max_keypoints == 77
    monkeypatch.setenv("DHPTAM_WEIGHTS_DIR", str(shared_path("models", "r2d2")))
    extractor = features.from_config(
        Config.from_toml('[features]\nweights = "faster2d2_WASF_N16"\ndevice = "cpu"\nmax_keypoints = 10')
    )
    assert extractor.name == "r2d2" and "Fast_Quad_L2Net" in repr(extractor)
    assert len(extractor.extract_one(_camera())) == 10
    # The fast CPU setting from the section: one scale, bfloat16 trunk.
    fast = Config.from_toml(
        '[features]\nweights = "faster2d2_WASF_N16"\ndevice = "cpu"\nprecision = "bfloat16"\nscales = [1.0]'
    )
    extractor = features.from_config(fast)
    assert (extractor.precision, extractor.scales) == ("bfloat16", (1.0,))  # type: ignore[attr-defined]
    # Arguments take precedence over the section.
    extractor = features.from_config(fast, precision="float32", scales=(1.0, 0.5))
    assert (extractor.precision, extractor.scales) == ("float32", (1.0, 0.5))  # type: ignore[attr-defined]


def test_the_shipped_r2d2_cpu_configuration_builds_the_fast_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    # configs/r2d2-cpu.toml, the file docs/FEATURES.md and the README point CPU users to.
    monkeypatch.setenv("DHPTAM_WEIGHTS_DIR", str(shared_path("models", "r2d2")))
    path = Path(__file__).resolve().parents[1] / "configs" / "r2d2-cpu.toml"
    config = Config.from_file(path)
    extractor = features.from_config(config)
    assert "Fast_Quad_L2Net" in repr(extractor) and extractor.device.type == "cpu"  # type: ignore[attr-defined]
    assert (extractor.precision, extractor.scales) == ("int8", (1.0,))  # type: ignore[attr-defined]
    # R2D2 keeps the plain keyframe floor on DVS-biased frames (docs/BENCHMARKS.md).
    assert config.to_dict()["tracking"]["dvs_keyframe_min_tracked"] == 50


def test_the_shipped_r2d2_one_scale_configuration_builds_its_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    # configs/r2d2-one-scale.toml: the smaller network at one scale, float32, on any device.
    monkeypatch.setenv("DHPTAM_WEIGHTS_DIR", str(shared_path("models", "r2d2")))
    path = Path(__file__).resolve().parents[1] / "configs" / "r2d2-one-scale.toml"
    extractor = features.from_config(Config.from_file(path), device="cpu")
    assert "Fast_Quad_L2Net" in repr(extractor)
    assert (extractor.precision, extractor.scales) == ("float32", (1.0,))  # type: ignore[attr-defined]
    assert extractor.scales_for(320, 320) == [1.0]  # type: ignore[attr-defined]


def test_the_default_keypoint_budget_follows_the_image_size() -> None:
    # One keypoint per 256 px², within [1000, 8000].
    assert features.keypoint_budget(320, 320) == 1000  # the floor (400 by area)
    assert features.keypoint_budget(1024, 1024) == 4096
    assert features.keypoint_budget(1280, 720) == 3600
    assert features.keypoint_budget(4096, 4096) == 8000  # the cap
    with pytest.raises(InputError, match="image size"):
        features.keypoint_budget(0, 480)
    orb = Config.from_toml('[features]\nextractor = "orb"')
    assert orb.to_dict()["features"]["max_keypoints"] == 0  # the default: from the size
    assert features.from_config(orb, image_size=(1024, 1024)).max_keypoints == 4096
    assert features.from_config(orb).max_keypoints == 1000  # no size given: the floor
    explicit = Config.from_toml('[features]\nextractor = "orb"\nmax_keypoints = 77')
    assert features.from_config(explicit, image_size=(1024, 1024)).max_keypoints == 77


def _run_python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120
    )


def test_importing_dhptam_features_does_not_import_torch() -> None:
    result = _run_python(
        """
        import sys
        import dhptam, dhptam.features
        dhptam.features.load("orb")
        print("torch" in sys.modules)
        """
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "False"


def test_without_torch_orb_and_sift_run_and_learned_extractors_say_how_to_install() -> None:
    result = _run_python(
        """
        import sys

        class NoTorch:
            def find_spec(self, name, path=None, target=None):
                if name == "torch" or name.startswith("torch."):
                    raise ImportError("No module named 'torch' (blocked by the test)")
                return None

        sys.meta_path.insert(0, NoTorch())
        import numpy as np
        from dhptam import features
        from dhptam.errors import DhptamError

        rng = np.random.default_rng(1)
        image = (rng.random((96, 128)) * 255).astype(np.uint8)
        for name in ("orb", "sift"):
            left, right = features.load(name).extract(image, image)
            assert len(features.match(left, right)[0]) > 10, name
        for name in ("r2d2", "superpoint"):
            try:
                features.load(name)
            except DhptamError as e:
                assert isinstance(e, ImportError)
                print(name, e)
        """
    )
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 2
    assert all("pip install dhptam[features]" in line for line in lines)


def test_r2d2_architectures_match_the_official_checkpoints() -> None:
    from dhptam.features.r2d2 import architecture_from_string, load_checkpoint

    quad = architecture_from_string("Quad_L2Net_ConfCFS()")
    assert [c.dilation for c in quad.convs] == [1, 1, 1, 2, 4, 4, 4, 8, 16] and quad.upsample == 1
    fast = architecture_from_string("Fast_Quad_L2Net_ConfCFS()")
    assert [c.pool_after for c in fast.convs][2] == 2 and fast.upsample == 2
    for name in ("r2d2_WASF_N16", "faster2d2_WASF_N16"):
        net = load_checkpoint(shared_path("models", "r2d2", f"{name}.pt"))
        x = torch.randn(2, 3, 48, 64)
        with torch.inference_mode():
            plain = net(x)
            net.fuse()
            folded = net(x)
        for a, b in zip(plain, folded, strict=True):
            torch.testing.assert_close(a, b, atol=1e-4, rtol=1e-4)
        descriptors, reliability, repeatability = folded
        assert descriptors.shape == (2, 128, 48, 64) and reliability.shape == (2, 1, 48, 64)
        assert float(repeatability.min()) >= 0 and float(repeatability.max()) <= 1
    with pytest.raises(InputError, match="net"):
        architecture_from_string("__import__('os').system('true')")
    with pytest.raises(InputError, match="unsupported arguments"):
        architecture_from_string("Quad_L2Net_ConfCFS(bn_affine=True)")


def test_r2d2_pyramid_scales_and_thresholds() -> None:
    path = shared_path("models", "r2d2", "r2d2_WASF_N16.pt")
    extractor = features.load("r2d2", path, device="cpu", max_keypoints=5000)
    assert extractor.scales_for(480, 640) == [1.0, 0.75, 0.5]  # type: ignore[attr-defined]
    assert extractor.scales_for(180, 240) == [1.0, 0.75]  # type: ignore[attr-defined]
    image = _camera()
    many = extractor.extract_one(image)
    assert many.scores.min() >= 0.7 * 0.7 - 1e-6  # reliability × repeatability, both ≥ 0.7
    strict = features.load(
        "r2d2", path, device="cpu", max_keypoints=5000, reliability_threshold=0.9, repeatability_threshold=0.9
    ).extract_one(image)
    assert 0 < len(strict) < len(many) and strict.scores.min() >= 0.81 - 1e-6
    # Merging the scales leaves no two keypoints within 2 px (Chebyshev) of each other.
    d = np.abs(many.keypoints[:, None, :] - many.keypoints[None, :, :]).max(axis=2)
    np.fill_diagonal(d, np.inf)
    assert d.min() > 1.0
    unmerged = features.load("r2d2", path, device="cpu", max_keypoints=5000, merge_radius_px=0).extract_one(
        image
    )
    assert len(unmerged) > len(many)


def test_bfloat16_trunk_agrees_with_float32() -> None:
    image = _camera()
    path = shared_path("models", "r2d2", "faster2d2_WASF_N16.pt")
    full = features.load("r2d2", path, device="cpu", max_keypoints=200).extract_one(image)
    half = features.load("r2d2", path, device="cpu", max_keypoints=200, precision="bfloat16").extract_one(
        image
    )
    assert half.descriptors.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(half.descriptors, axis=1), 1.0, atol=1e-5)
    # Most keypoints are found again within 1 px, with nearly the same descriptor (measured:
    # 98.5 % of them, median cosine 0.99996).
    d = np.linalg.norm(full.keypoints[:, None] - half.keypoints[None], axis=2)
    near = d.min(axis=1) <= 1.0
    assert near.mean() > 0.9
    same = np.einsum("ij,ij->i", full.descriptors[near], half.descriptors[d.argmin(axis=1)[near]])
    assert np.median(same) > 0.995
    with pytest.raises(InputError, match="precision"):
        features.load("r2d2", path, device="cpu", precision="int4")


def _grey(name: str, width: int = 240, height: int = 180) -> npt.NDArray[np.uint8]:
    image = getattr(data, name)()
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("checkpoint", ["faster2d2_WASF_N16", "r2d2_WASF_N16"])
def test_int8_trunk_agrees_with_float32(checkpoint: str) -> None:
    image = _camera()
    path = shared_path("models", "r2d2", f"{checkpoint}.pt")
    full = features.load("r2d2", path, device="cpu", max_keypoints=200).extract_one(image)
    # Calibrated on another photograph, as a user would (never on the image under test).
    quantised = features.load(
        "r2d2", path, device="cpu", max_keypoints=200, precision="int8", calibration_images=[_grey("chelsea")]
    )
    assert "int8" in repr(quantised)
    q = quantised.extract_one(image)
    assert q.descriptors.dtype == np.float32 and q.keypoints.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(q.descriptors, axis=1), 1.0, atol=1e-5)
    # Measured on an AVX2 CPU without VNNI: 92 % (faster2d2) and 88.5 % (r2d2) of the float32
    # keypoints found again within 1 px, median descriptor cosine 0.998 and 0.996 (10th
    # percentile 0.985, 0.987). With 8-bit activations this CPU's 16-bit sums saturate: 49 %.
    d = np.linalg.norm(full.keypoints[:, None] - q.keypoints[None], axis=2)
    near = d.min(axis=1) <= 1.0
    assert near.mean() > 0.75
    same = np.einsum("ij,ij->i", full.descriptors[near], q.descriptors[d.argmin(axis=1)[near]])
    assert np.median(same) > 0.99
    assert np.percentile(same, 10) > 0.93


def test_int8_calibrates_on_the_first_image_once() -> None:
    image, other = _camera(), _grey("chelsea")
    path = shared_path("models", "r2d2", "faster2d2_WASF_N16.pt")
    common = dict(device="cpu", max_keypoints=200, precision="int8", scales=(1.0,))
    lazy = features.load("r2d2", path, **common)  # type: ignore[arg-type]
    explicit = features.load("r2d2", path, calibration_images=[image], **common)  # type: ignore[arg-type]
    # Calibrating on the left image of the first pair is the same as passing it as the
    # calibration set ...
    first = lazy.extract(image, other)
    again = explicit.extract(image, other)
    # ... and later calls keep that calibration.
    lazy.extract_one(other)
    later = lazy.extract_one(image)
    assert len(first[0]) > 50 and len(first[1]) > 50
    for a, b in ((first[0], again[0]), (first[1], again[1]), (first[0], later)):
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        np.testing.assert_array_equal(a.scores, b.scores)
        np.testing.assert_array_equal(a.descriptors, b.descriptors)
    # Calibrated on the other image instead, the results differ (the calibration is used).
    moved = features.load("r2d2", path, calibration_images=[other], **common).extract_one(image)  # type: ignore[arg-type]
    assert not np.array_equal(moved.scores, later.scores)


def test_int8_refuses_bad_settings() -> None:
    path = shared_path("models", "r2d2", "faster2d2_WASF_N16.pt")
    with pytest.raises(InputError, match="calibration_images: only used with precision='int8'"):
        features.load("r2d2", path, device="cpu", calibration_images=[_camera()])
    with pytest.raises(InputError, match="calibration_images: expected at least one image"):
        features.load("r2d2", path, device="cpu", precision="int8", calibration_images=[])
    colour = cv2.resize(data.chelsea(), (64, 48))
    with pytest.raises(InputError, match=r"calibration_images\[1\]: expected an 8-bit grayscale"):
        features.load("r2d2", path, device="cpu", precision="int8", calibration_images=[_camera(), colour])
    with pytest.raises(InputError, match="precision: expected one of float32, bfloat16, float16, int8"):
        features.load("r2d2", path, device="cpu", precision="int4")
    with pytest.raises(InputError, match="precision: expected one of float32, bfloat16, float16, got 'int8'"):
        SuperPoint(None, net=SuperPointNet(), device="cpu", precision="int8")


@pytest.mark.parametrize("radius", [0, 1, 2, 4, 7])
def test_window_max_equals_max_pool(radius: int) -> None:
    from dhptam.features.base import window_max

    x = torch.randn(2, 3, 37, 53)
    expected = torch.nn.functional.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius)
    torch.testing.assert_close(window_max(x, radius), expected, rtol=0, atol=0)


@pytest.mark.parametrize("checkpoint", ["faster2d2_WASF_N16", "r2d2_WASF_N16"])
def test_r2d2_cpu_heads_equal_the_network_on_the_upsampled_map(checkpoint: str) -> None:
    # The CPU path never builds the upsampled 128-channel map: the Rust core evaluates the
    # heads from the low-resolution map and descriptors are interpolated at the keypoints.
    # Both must equal the published network run the straightforward way.
    from dhptam.features.r2d2 import _sample_upsampled, load_checkpoint

    net = load_checkpoint(shared_path("models", "r2d2", f"{checkpoint}.pt"))
    net.fuse()
    x = torch.randn(2, 3, 62, 86, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        full = net.trunk(x)
        _, reliability, repeatability = net.heads(full)
        low = net.trunk(x, upsample=False)
        weights, bias = (t.numpy() for t in net.head_weights())
        up = net.arch.upsample
        nhwc = low.permute(0, 2, 3, 1).contiguous()
        rel, rep = _core._r2d2_heads(nhwc.numpy(), weights, bias, up)
        np.testing.assert_allclose(rel, reliability[:, 0].numpy(), atol=2e-6)
        np.testing.assert_allclose(rep, repeatability[:, 0].numpy(), atol=2e-6)
        # bfloat16 maps go over as bit patterns and read as their float32 values.
        low16 = nhwc.to(torch.bfloat16)
        rel16, _ = _core._r2d2_heads(low16.view(torch.int16).numpy(), weights, bias, up)
        rel32, _ = _core._r2d2_heads(low16.float().numpy(), weights, bias, up)
        np.testing.assert_array_equal(rel16, rel32)
        # Corners, edges and the interior of both images.
        h, w = full.shape[2:]
        b = torch.tensor([0, 1, 0, 1, 1])
        ys = torch.tensor([0, h - 1, 0, h // 2 + 1, 7])
        xs = torch.tensor([0, w - 1, w - 1, w // 2, 0])
        np.testing.assert_allclose(_sample_upsampled(low, b, ys, xs, up), full[b, :, ys, xs], atol=1e-6)
    with pytest.raises(InputError, match="upsample"):
        _core._r2d2_heads(nhwc.numpy(), weights, bias, 3)
    with pytest.raises(InputError, match="weights"):
        _core._r2d2_heads(nhwc.numpy(), weights[:, :-1].copy(), bias, up)

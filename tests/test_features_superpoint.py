"""SuperPoint: both published checkpoint layouts load, and the extractor equals a plain reference.

No SuperPoint weights ship with the repository (Magic Leap's licence), so the tests write
checkpoints with random weights in each layout. The reference below recomputes everything the
extractor does, step by step, with ``F.conv2d`` on the raw tensors and numpy loops for the rest.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import pytest
import torch
import torch.nn.functional as F  # noqa: N812
from scipy.ndimage import maximum_filter
from skimage import data

from dhptam import features
from dhptam.errors import FileError
from dhptam.features.superpoint import SuperPointNet

ORIGINAL_KEYS = [
    f"{name}.{leaf}"
    for name in [
        "conv1a", "conv1b", "conv2a", "conv2b", "conv3a", "conv3b", "conv4a", "conv4b",
        "convPa", "convPb", "convDa", "convDb",
    ]
    for leaf in ("weight", "bias")
]  # fmt: skip


def _random_state(seed: int = 3) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    state = SuperPointNet().state_dict()
    # Sharper detector logits than the default initialisation, so the heat map has clear peaks.
    state["convPb.weight"] = state["convPb.weight"] * 20.0
    return {k: v.clone() for k, v in state.items()}


def _hf_layout(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The same tensors under Hugging Face transformers' SuperPoint names."""
    names = {f"conv{b + 1}{ab}": f"encoder.conv_blocks.{b}.conv_{ab}" for b in range(4) for ab in "ab"}
    names |= {
        "convPa": "keypoint_decoder.conv_score_a",
        "convPb": "keypoint_decoder.conv_score_b",
        "convDa": "descriptor_decoder.conv_descriptor_a",
        "convDb": "descriptor_decoder.conv_descriptor_b",
    }
    out = {}
    for key, value in state.items():
        stem, leaf = key.rsplit(".", 1)
        out[f"{names[stem]}.{leaf}"] = value
    return out


def _image() -> npt.NDArray[np.uint8]:
    # 92×70: not multiples of 8, so the padding path is exercised too.
    return cv2.resize(data.camera(), (92, 70), interpolation=cv2.INTER_AREA)


def _reference(
    state: dict[str, torch.Tensor], image: npt.NDArray[np.uint8], k: int, radius: int = 4, border: int = 4
) -> tuple[npt.NDArray, npt.NDArray, npt.NDArray]:
    """Keypoints, scores, descriptors computed the plain way."""
    h, w = image.shape
    padded = np.pad(image, ((0, (-h) % 8), (0, (-w) % 8)), mode="edge").astype(np.float32) / 255.0
    x = torch.from_numpy(padded)[None, None]

    def conv(t: torch.Tensor, name: str, relu: bool = True) -> torch.Tensor:
        weight = state[f"{name}.weight"]
        out = F.conv2d(t, weight, state[f"{name}.bias"], padding=weight.shape[-1] // 2)
        return F.relu(out) if relu else out

    for block in range(4):
        x = conv(conv(x, f"conv{block + 1}a"), f"conv{block + 1}b")
        if block < 3:
            x = F.max_pool2d(x, 2)
    logits = conv(conv(x, "convPa"), "convPb", relu=False)[0].numpy().astype(np.float64)
    desc = conv(conv(x, "convDa"), "convDb", relu=False)[0].numpy().astype(np.float64)

    prob = np.exp(logits - logits.max(axis=0))
    prob /= prob.sum(axis=0)
    hc, wc = prob.shape[1:]
    heat = np.zeros((hc * 8, wc * 8))
    for cy in range(hc):
        for cx in range(wc):
            for r in range(8):
                for c in range(8):
                    heat[cy * 8 + r, cx * 8 + c] = prob[r * 8 + c, cy, cx]
    heat = heat[:h, :w]

    size = 2 * radius + 1
    is_max = heat == maximum_filter(heat, size=size, mode="constant", cval=-np.inf)
    for _ in range(2):
        covered = maximum_filter(is_max.astype(float), size=size, mode="constant", cval=0.0) > 0
        remaining = np.where(covered, 0.0, heat)
        is_max |= (
            remaining == maximum_filter(remaining, size=size, mode="constant", cval=-np.inf)
        ) & ~covered
    nms = np.where(is_max, heat, 0.0)
    nms[:border], nms[h - border :], nms[:, :border], nms[:, w - border :] = 0, 0, 0, 0
    ys, xs = np.nonzero(nms > 0.005)
    scores = nms[ys, xs]
    order = np.argsort(-scores, kind="stable")[:k]
    ys, xs, scores = ys[order], xs[order], scores[order]

    keypoints = []
    for y, x0 in zip(ys, xs, strict=True):
        offset = []
        for axis_samples in (
            (heat[y, x0 - 1], heat[y, x0], heat[y, x0 + 1]),
            (heat[y - 1, x0], heat[y, x0], heat[y + 1, x0]),
        ):
            a, b, c = axis_samples
            den = 2 * (2 * b - a - c)
            offset.append(float(np.clip((c - a) / den, -0.5, 0.5)) if den > 1e-12 else 0.0)
        keypoints.append((x0 + offset[0], y + offset[1]))
    keypoints_arr = np.array(keypoints)

    desc /= np.linalg.norm(desc, axis=0, keepdims=True)
    sampled = []
    for kx, ky in keypoints_arr:
        u, v = (kx + 0.5) / 8 - 0.5, (ky + 0.5) / 8 - 0.5  # position on the 1/8 grid
        u0, v0 = int(np.floor(u)), int(np.floor(v))
        fu, fv = u - u0, v - v0
        d = (
            desc[:, v0, u0] * (1 - fu) * (1 - fv)
            + desc[:, v0, u0 + 1] * fu * (1 - fv)
            + desc[:, v0 + 1, u0] * (1 - fu) * fv
            + desc[:, v0 + 1, u0 + 1] * fu * fv
        )
        sampled.append(d / np.linalg.norm(d))
    return keypoints_arr, scores, np.array(sampled)


def _save(state: dict[str, torch.Tensor], path: Path) -> Path:
    torch.save(state, path)
    return path


@pytest.mark.parametrize("layout", ["original", "transformers", "transformers-prefixed"])
def test_each_published_layout_loads_and_equals_the_reference(tmp_path: Path, layout: str) -> None:
    state = _random_state()
    if layout == "original":
        saved = state
        assert sorted(saved) == sorted(ORIGINAL_KEYS)
    elif layout == "transformers":
        saved = _hf_layout(state)
    else:
        saved = {f"superpoint.{k}": v for k, v in _hf_layout(state).items()}
    extractor = features.load("superpoint", _save(saved, tmp_path / "sp.pth"), device="cpu", max_keypoints=60)
    image = _image()
    got = extractor.extract_one(image)
    kp, scores, desc = _reference(state, image, k=60)
    assert 30 < len(got) <= 60 and len(got) == len(kp)
    np.testing.assert_allclose(got.keypoints, kp, atol=1e-4)
    np.testing.assert_allclose(got.scores, scores, rtol=1e-5)
    np.testing.assert_allclose(got.descriptors, desc, atol=1e-5)
    # The stereo path (one batch of two) gives the same as two single images.
    left, right = extractor.extract(image, image[:, ::-1])
    np.testing.assert_allclose(left.keypoints, got.keypoints, atol=1e-5)
    np.testing.assert_allclose(right.keypoints, extractor.extract_one(image[:, ::-1]).keypoints, atol=1e-5)


def test_top_k_keeps_the_best_scores(tmp_path: Path) -> None:
    state = _random_state(seed=5)
    path = _save(state, tmp_path / "sp.pth")
    all_points = features.load("superpoint", path, device="cpu", max_keypoints=10_000).extract_one(_image())
    best = features.load("superpoint", path, device="cpu", max_keypoints=7).extract_one(_image())
    np.testing.assert_array_equal(best.keypoints, all_points.keypoints[:7])
    assert best.scores.min() >= all_points.scores[7:].max()


def test_a_checkpoint_of_another_network_is_refused(tmp_path: Path) -> None:
    state = _random_state()
    del state["convDb.bias"]
    with pytest.raises(FileError, match=r"superpoint_v1\.pth or transformers layout"):
        features.load("superpoint", _save(state, tmp_path / "broken.pth"), device="cpu")

"""SuperPoint (DeTone, Malisiewicz, Rabinovich, CVPRW 2018), written here in torch.

Network: a VGG-style encoder of eight 3×3 convolutions with ReLU (64, 64 | 64, 64 | 128, 128 |
128, 128 channels, 2×2 max pooling after each of the first three pairs, so 1/8 resolution),
and two heads on it, each a 3×3 convolution to 256 channels with ReLU then a 1×1 convolution:
the detector to 65 channels (an 8×8 cell of pixels plus a "no keypoint" dustbin), the descriptor
to 256 channels.

Detection: softmax over the 65 channels, dustbin dropped, the 64 remaining channels of each cell
laid back out as its 8×8 pixels (channel c = 8·row + column) into a full-resolution heat map;
non-maximum suppression of radius ``nms_radius`` (a max-pool based suppression run twice so that
points next to a suppressed maximum can come back); keypoints with a score above
``detection_threshold``, farther than ``remove_borders`` pixels from the border; the
``max_keypoints`` best; positions refined to sub-pixel with a parabola through the heat map.

Description: the descriptor map is L2-normalised, sampled bilinearly (``grid_sample``) at each
keypoint — pixel x of the image lies at (x + 0.5) / 8 − 0.5 on the 1/8 grid — and normalised
again. Descriptors are 256-D unit-norm float32.

Checkpoints in two published key layouts load here:

* the original ``superpoint_v1.pth`` of Magic Leap (``conv1a.weight`` … ``conv4b``, ``convPa``,
  ``convPb``, ``convDa``, ``convDb``), the layout this module uses itself;
* the PyTorch re-implementation in Hugging Face ``transformers``
  (``encoder.conv_blocks.{0..3}.conv_{a,b}``, ``keypoint_decoder.conv_score_{a,b}``,
  ``descriptor_decoder.conv_descriptor_{a,b}``, optionally under a ``superpoint.`` prefix),
  whose tensors are the same weights under other names.

Images whose sides are not multiples of 8 are padded on the bottom/right by edge replication
and the heat map is cropped back.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F  # noqa: N812 - torch's usual name
from torch import nn

from ..errors import FileError
from .base import Features, TorchExtractor, refine_subpixel, to_features, window_max
from .weights import safe_torch_load

__all__ = ["SuperPoint", "SuperPointNet", "convert_state_dict", "simple_nms"]

# (name, input channels, output channels) of the encoder's convolutions, in order.
_ENCODER = (
    ("conv1a", 1, 64), ("conv1b", 64, 64), ("conv2a", 64, 64), ("conv2b", 64, 64),
    ("conv3a", 64, 128), ("conv3b", 128, 128), ("conv4a", 128, 128), ("conv4b", 128, 128),
)  # fmt: skip


class SuperPointNet(nn.Module):
    """The SuperPoint network; parameter names follow the original ``superpoint_v1.pth``."""

    def __init__(self, descriptor_dim: int = 256) -> None:
        super().__init__()
        for name, cin, cout in _ENCODER:
            setattr(self, name, nn.Conv2d(cin, cout, kernel_size=3, padding=1))
        self.convPa = nn.Conv2d(128, 256, kernel_size=3, padding=1)
        self.convPb = nn.Conv2d(256, 65, kernel_size=1)
        self.convDa = nn.Conv2d(128, 256, kernel_size=3, padding=1)
        self.convDb = nn.Conv2d(256, descriptor_dim, kernel_size=1)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (B, 1, H, W) in [0, 1], H and W multiples of 8.

        Returns the heat map (B, 1, H, W) and the raw descriptor map (B, D, H/8, W/8).
        """
        x = image
        for i, (name, _, _) in enumerate(_ENCODER):
            x = F.relu(getattr(self, name)(x))
            if i in (1, 3, 5):
                x = F.max_pool2d(x, 2)
        logits = self.convPb(F.relu(self.convPa(x)))
        # float32 from here on even under autocast: the heat map is thresholded and compared
        # with its neighbours, which bfloat16's 8-bit mantissa would turn into ties.
        prob = F.softmax(logits.float(), dim=1)[:, :64]
        heat = F.pixel_shuffle(prob, 8)  # channel 8·r + c of a cell → pixel (r, c) of the cell
        descriptors = self.convDb(F.relu(self.convDa(x)))
        return heat, descriptors


# Hugging Face transformers' names → the original names.
_HF_NAMES = {
    **{
        f"encoder.conv_blocks.{block}.conv_{ab}": f"conv{block + 1}{ab}"
        for block in range(4)
        for ab in ("a", "b")
    },
    "keypoint_decoder.conv_score_a": "convPa",
    "keypoint_decoder.conv_score_b": "convPb",
    "descriptor_decoder.conv_descriptor_a": "convDa",
    "descriptor_decoder.conv_descriptor_b": "convDb",
}


def convert_state_dict(state: dict[str, Any]) -> dict[str, Any]:
    """A SuperPoint state dict in either published layout, renamed to the original layout.

    Prefixes ``module.`` (DataParallel) and ``superpoint.`` are dropped first.

    >>> sorted(convert_state_dict({"encoder.conv_blocks.1.conv_b.weight": 0, "convPa.bias": 1}))
    ['conv2b.weight', 'convPa.bias']
    """
    out = {}
    for key, value in state.items():
        key = re.sub(r"^(module\.|superpoint\.)+", "", key)
        stem, _, leaf = key.rpartition(".")
        out[f"{_HF_NAMES.get(stem, stem)}.{leaf}" if stem else key] = value
    return out


def load_network(path: str | Path) -> SuperPointNet:
    """A :class:`SuperPointNet` with the weights of a checkpoint in either layout, in eval mode."""
    path = Path(path)
    checkpoint = safe_torch_load(path, "SuperPoint")
    state = checkpoint.get("state_dict", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict):
        raise FileError(f"{path}: expected a SuperPoint state dict", path=str(path))
    state = convert_state_dict(state)
    dim = state["convDb.weight"].shape[0] if "convDb.weight" in state else 256
    net = SuperPointNet(descriptor_dim=int(dim))
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise FileError(
            f"{path}: not a SuperPoint checkpoint in the superpoint_v1.pth or transformers layout: {e}",
            path=str(path),
        ) from e
    return net.eval()


def simple_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """Scores (B, 1, H, W) with everything but the local maxima within ``radius`` set to 0.

    A pixel is a maximum when it equals the maximum of its (2r+1)² window. Two more rounds
    then let a pixel count as a maximum once every maximum that covered it is itself suppressed
    around a stronger one, which recovers points beside a suppressed neighbour.
    """

    def pool(x: torch.Tensor) -> torch.Tensor:
        return window_max(x, radius)

    zeros = torch.zeros_like(scores)
    is_max = scores == pool(scores)
    for _ in range(2):
        covered = pool(is_max.float()) > 0
        remaining = torch.where(covered, zeros, scores)
        new_max = remaining == pool(remaining)
        is_max = is_max | (new_max & ~covered)
    return torch.where(is_max, scores, zeros)


def sample_descriptors(descriptors: torch.Tensor, keypoints: torch.Tensor, cell: int = 8) -> torch.Tensor:
    """Bilinear samples (N, D), unit-norm, of a (1, D, h, w) map at image pixels ``keypoints`` (N, 2).

    Image pixel x lies at (x + 0.5) / cell − 0.5 on the coarse grid; with
    ``align_corners=False`` that is the normalised coordinate 2 (x + 0.5) / (cell·w) − 1.
    """
    _, dim, h, w = descriptors.shape
    size = keypoints.new_tensor([cell * w, cell * h])
    grid = (2.0 * (keypoints + 0.5) / size - 1.0).view(1, 1, -1, 2)
    sampled = F.grid_sample(descriptors, grid, mode="bilinear", align_corners=False)
    return F.normalize(sampled.view(dim, -1).t(), p=2, dim=1)


class SuperPoint(TorchExtractor):
    """SuperPoint keypoints with 256-D unit-norm float32 descriptors (see the module docstring)."""

    name = "superpoint"
    descriptor_width = 256

    def __init__(
        self,
        weights: str | Path | None,
        *,
        max_keypoints: int = 1000,
        device: str | None = "auto",
        threads: int | None = None,
        precision: str = "float32",
        nms_radius: int = 4,
        detection_threshold: float = 0.005,
        remove_borders: int = 4,
        net: SuperPointNet | None = None,
    ) -> None:
        super().__init__(max_keypoints, device, threads, precision)
        if (weights is None) == (net is None):
            raise ValueError("SuperPoint: give exactly one of weights (a checkpoint path) and net")
        self.weights = Path(weights) if weights is not None else None
        self.net = load_network(weights) if weights is not None else net  # type: ignore[assignment]
        assert self.net is not None
        # NHWC: oneDNN's fast convolution kernels on the CPU, cuDNN's preferred layout on CUDA.
        self.net.eval().to(self.device, memory_format=torch.channels_last)
        self.descriptor_width = self.net.convDb.out_channels
        self.nms_radius = int(nms_radius)
        self.detection_threshold = float(detection_threshold)
        self.remove_borders = int(remove_borders)

    def _run_batch(self, images: list[npt.NDArray[np.uint8]]) -> list[Features]:
        with torch.inference_mode():
            batch = self._to_tensor(images)
            return self.detect(batch)

    def detect(self, batch: torch.Tensor) -> list[Features]:
        """Features of (B, 1, H, W) images in [0, 1] on the extractor's device."""
        height, width = batch.shape[-2:]
        pad_h, pad_w = (-height) % 8, (-width) % 8
        if pad_h or pad_w:
            batch = F.pad(batch, (0, pad_w, 0, pad_h), mode="replicate")
        with self.autocast():
            heat, raw_desc = self.net(batch)
        heat = heat[..., :height, :width].float()
        desc_map = F.normalize(raw_desc.float(), p=2, dim=1)
        suppressed = simple_nms(heat, self.nms_radius)
        border = self.remove_borders
        if border > 0:
            suppressed[..., :border, :] = 0
            suppressed[..., height - border :, :] = 0
            suppressed[..., :, :border] = 0
            suppressed[..., :, width - border :] = 0
        out = []
        for i in range(heat.shape[0]):
            ys, xs = torch.nonzero(suppressed[i, 0] > self.detection_threshold, as_tuple=True)
            scores = suppressed[i, 0, ys, xs]
            order = torch.argsort(scores, descending=True)[: self.max_keypoints]
            ys, xs, scores = ys[order], xs[order], scores[order]
            b = torch.full_like(xs, i)
            keypoints = torch.stack([xs, ys], dim=1).float() + refine_subpixel(heat, b, ys, xs)
            descriptors = sample_descriptors(desc_map[i : i + 1], keypoints)
            out.append(to_features(keypoints, scores, descriptors))
        return out

    def __repr__(self) -> str:
        return f"SuperPoint(weights={self.weights}, max_keypoints={self.max_keypoints}, device={self.device})"

"""R2D2 (Revaud et al., NeurIPS 2019): repeatable and reliable keypoints with descriptors.

The network is the published one, rebuilt here from the architecture string that every official
checkpoint carries in its ``net`` field:

* ``Quad_L2Net_ConfCFS()`` (``r2d2_WASF_N16.pt``): nine convolutions at full resolution, the
  strides of the L2-Net turned into dilations (1, 1, 1, 2, 4, 4, then three 2×2 convolutions
  with dilations 4, 8, 16), batch norms without affine parameters, 128 output channels;
* ``Fast_Quad_L2Net_ConfCFS()`` (``faster2d2_WASF_N16.pt``): the same after a 2× max pooling
  following the third convolution, dilations halved, and a bilinear 2× upsampling at the end.

Heads, applied to the squared features x²: reliability = softmax of a 1×1 convolution with two
outputs (second class); repeatability = softplus(s) / (1 + softplus(s)) of a 1×1 convolution with
one output (the published model's choice). Descriptors are the L2-normalised 128 channels.

Detection, per image and scale: a pixel is a keypoint when its repeatability equals the 3×3
maximum around it and both repeatability ≥ ``repeatability_threshold`` and reliability ≥
``reliability_threshold`` (0.7 and 0.7 as in the authors' extractor). Its score is
reliability × repeatability; its position is refined to sub-pixel accuracy with a parabola on
the repeatability map. Scales: the image at ``scales`` (default 1, 0.75, 0.5 of its size),
skipping any whose longer side would fall under ``min_size`` pixels (default 160); the authors
use 2^(1/4) steps from 1024 px down to 256 px (up to 9 scales), which costs about twice as much
for little gain at SLAM image sizes. Points found at several scales are merged by a non-maximum
suppression of radius ``merge_radius_px`` in the full image (otherwise the copies of one point
defeat the ratio test of matching). The ``max_keypoints`` best scores are kept.

Both images of a stereo pair go through the network as one batch per scale. Inference folds the
batch norms into the convolutions (exact up to float rounding) and runs under
``torch.inference_mode``. The fast variant's final upsampling is never applied to the whole
128-channel map: descriptors are interpolated at the keypoints only, and on the CPU the heads
run in the Rust core (``_core._r2d2_heads``), which interpolates, squares and projects each
pixel's descriptor in one pass (equal to the torch path to float rounding; tested).

``precision="int8"`` (CPU only) runs the trunk quantised by ``torch.ao.quantization``: static
post-training quantisation for torch's oneDNN engine, weights per output channel (symmetric
int8), activations per tensor (unsigned, 7 bits: see :func:`quantize_trunk`; ranges = minimum
and maximum seen), each
convolution fused with its ReLU, the 2× max pooling done on the int8 map, the output
dequantised to float32 for the heads and descriptors. The activation ranges come from
``calibration_images`` when given, else from the first image the extractor sees (the left one
of the first pair), shrunk to at most 640×480 pixels (so the first call is slower and the
results depend on that image; pass the same calibration images to make two extractors
agree). Activations take a quarter of float32's bytes and half of bfloat16's, and the
full-resolution trunk is bounded by memory traffic on a CPU (docs/BENCHMARKS.md). Quality
against float32: ``tests/test_features.py`` and ``tests/test_features_quality.py``.
"""

from __future__ import annotations

import ast
import contextlib
import copy
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
import torch.nn.functional as F  # noqa: N812 - torch's usual name
from torch import nn

from .. import _core
from ..errors import FileError, InputError
from .base import Features, TorchExtractor, check_image, refine_subpixel, to_features, window_max
from .weights import safe_torch_load

__all__ = ["R2D2", "R2D2Net", "architecture_from_string", "load_checkpoint", "quantize_trunk"]

# ImageNet statistics the published models were trained with (RGB); a grey image is fed as
# three equal channels.
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class _Conv:
    """One convolution of the trunk, in the published order."""

    out_channels: int
    kernel: int
    dilation: int
    batch_norm: bool
    relu: bool
    pool_after: int  # max-pooling factor applied after the activation (1: none)


@dataclass(frozen=True)
class Architecture:
    """The trunk of a Quad_L2Net-family network."""

    name: str
    convs: tuple[_Conv, ...]
    upsample: int  # bilinear upsampling factor at the end (1: none)
    dim: int


_KNOWN = {"Quad_L2Net_ConfCFS", "Fast_Quad_L2Net_ConfCFS"}
_ALLOWED_KWARGS = {"dim", "mchan", "relu22", "downsample_factor"}


def architecture_from_string(net: str) -> Architecture:
    """The architecture named by a checkpoint's ``net`` string, e.g. ``"Quad_L2Net_ConfCFS()"``.

    Keyword arguments are read as literals (never evaluated as code); the supported ones are
    ``dim``, ``mchan``, ``relu22`` and ``downsample_factor`` (Fast only).

    >>> arch = architecture_from_string("Fast_Quad_L2Net_ConfCFS()")
    >>> [c.dilation for c in arch.convs], arch.upsample
    ([1, 1, 1, 1, 2, 2, 2, 4, 8], 2)
    """
    match = re.fullmatch(r"\s*(\w+)\s*\((.*)\)\s*", net)
    if match is None or match.group(1) not in _KNOWN:
        raise InputError(
            f"net: expected one of {sorted(_KNOWN)} with optional keyword arguments, got {net!r}", field="net"
        )
    name, args = match.group(1), match.group(2).strip()
    kwargs: dict[str, Any] = {}
    if args:
        try:
            call = ast.parse(f"f({args})", mode="eval").body
            assert isinstance(call, ast.Call) and not call.args
            kwargs = {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords if kw.arg is not None}
        except (SyntaxError, ValueError, AssertionError) as e:
            raise InputError(f"net: cannot read the arguments of {net!r}", field="net") from e
    unknown = set(kwargs) - _ALLOWED_KWARGS
    if unknown:
        raise InputError(f"net: unsupported arguments {sorted(unknown)} in {net!r}", field="net")
    dim = int(kwargs.get("dim", 128))
    mchan = int(kwargs.get("mchan", 4))
    relu22 = bool(kwargs.get("relu22", False))
    fast = name.startswith("Fast_")
    down = int(kwargs.get("downsample_factor", 2)) if fast else 1

    # (out, kernel, stride, extra dilation, bn, relu, pool): the authors' layer list. In their
    # "dilated" mode a stride s becomes stride 1 and multiplies the dilation of every later
    # layer by s, so the output keeps the input's resolution.
    layers = [
        (8 * mchan, 3, 1, 1, True, True, 1),
        (8 * mchan, 3, 1, 1, True, True, 1),
        (16 * mchan, 3, 1 if fast else 2, 1, True, True, down),
        (16 * mchan, 3, 1, 1, True, True, 1),
        (32 * mchan, 3, 2, 2, True, True, 1),
        (32 * mchan, 3, 1, 1, True, True, 1),
        (32 * mchan, 2, 2, 1, True, relu22, 1),
        (32 * mchan, 2, 2, 1, True, relu22, 1),
        (dim, 2, 2, 1, False, False, 1),
    ]
    convs = []
    dilation = 1
    for out, k, stride, extra, bn, relu, pool in layers:
        convs.append(_Conv(out, k, dilation * extra, bn, relu, pool))
        dilation *= stride
    return Architecture(name, tuple(convs), down, dim)


class R2D2Net(nn.Module):
    """The published network; ``ops`` mirrors the authors' module list so checkpoints load as-is."""

    def __init__(self, arch: Architecture) -> None:
        super().__init__()
        self.arch = arch
        ops: list[nn.Module] = []
        channels = 3
        for conv in arch.convs:
            pad = ((conv.kernel - 1) * conv.dilation) // 2
            ops.append(
                nn.Conv2d(channels, conv.out_channels, conv.kernel, padding=pad, dilation=conv.dilation)
            )
            if conv.batch_norm:
                ops.append(nn.BatchNorm2d(conv.out_channels, affine=False))
            if conv.relu:
                ops.append(nn.ReLU(inplace=True))
            if conv.pool_after > 1:
                ops.append(nn.MaxPool2d(conv.pool_after))
            channels = conv.out_channels
        if arch.upsample > 1:
            ops.append(nn.Upsample(scale_factor=arch.upsample, mode="bilinear", align_corners=False))
        self.ops = nn.ModuleList(ops)
        self.clf = nn.Conv2d(arch.dim, 2, kernel_size=1)
        self.sal = nn.Conv2d(arch.dim, 1, kernel_size=1)
        self._fused: nn.Sequential | None = None

    def fuse(self) -> None:
        """Folds each batch norm into the convolution before it, for inference.

        With running mean μ, variance σ² and ε, BN(conv(x)) = w'·x + b' where
        w' = w / √(σ² + ε) and b' = (b − μ) / √(σ² + ε), channel by channel.
        """
        fused: list[nn.Module] = []
        for op in self.ops:
            if isinstance(op, nn.BatchNorm2d):
                conv = fused[-1]
                assert isinstance(conv, nn.Conv2d) and conv.bias is not None
                assert op.running_mean is not None and op.running_var is not None
                inv_std = torch.rsqrt(op.running_var + op.eps)
                folded = nn.Conv2d(
                    conv.in_channels,
                    conv.out_channels,
                    conv.kernel_size,  # type: ignore[arg-type]
                    padding=conv.padding,  # type: ignore[arg-type]
                    dilation=conv.dilation,  # type: ignore[arg-type]
                ).to(conv.weight.device)
                with torch.no_grad():
                    folded.weight.copy_(conv.weight * inv_std[:, None, None, None])
                    assert folded.bias is not None
                    folded.bias.copy_((conv.bias - op.running_mean) * inv_std)
                fused[-1] = folded
            elif isinstance(op, nn.ReLU):
                fused.append(nn.ReLU(inplace=True))
            else:
                fused.append(op)
        self._fused = nn.Sequential(*fused)

    def trunk(self, x: torch.Tensor, *, upsample: bool = True) -> torch.Tensor:
        """Normalised RGB (B, 3, H, W) → raw features (B, D, H, W).

        With ``upsample=False`` the final bilinear upsampling of the fast variant (always the
        last operation) is left out: (B, D, H / u, W / u) for ``u = arch.upsample``.
        """
        ops = self._fused if self._fused is not None else self.ops
        for op in ops:
            if not upsample and isinstance(op, nn.Upsample):
                break
            x = op(x)
        return x

    def head_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The heads' 1×1 convolutions as a (3, D) matrix (the two ``clf`` rows, then ``sal``)
        and a (3,) bias."""
        dim = self.arch.dim
        weights = torch.cat([self.clf.weight.reshape(2, dim), self.sal.weight.reshape(1, dim)])
        assert self.clf.bias is not None and self.sal.bias is not None
        bias = torch.cat([self.clf.bias, self.sal.bias])
        return weights.detach().float().contiguous(), bias.detach().float()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Normalised RGB (B, 3, H, W) → descriptors (B, D, H, W), reliability, repeatability (B, 1, H, W)."""
        features, reliability, repeatability = self.heads(self.trunk(x))
        return F.normalize(features, p=2, dim=1), reliability, repeatability

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Raw features → (the same raw features, reliability, repeatability).

        The descriptor map is left unnormalised: the extractor normalises only the rows it
        samples, which saves a pass over B × 128 × H × W values.
        """
        squared = x * x
        reliability = F.softmax(self.clf(squared), dim=1)[:, 1:2]
        s = F.softplus(self.sal(squared))
        repeatability = s / (1.0 + s)
        return x, reliability, repeatability


def _read_checkpoint(path: Path) -> dict[str, Any]:
    checkpoint = safe_torch_load(path, "R2D2")
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint or "net" not in checkpoint:
        raise FileError(
            f"{path}: expected an R2D2 checkpoint, a dict with 'net' (architecture string) and 'state_dict'",
            path=str(path),
        )
    return checkpoint


def load_checkpoint(path: str | Path) -> R2D2Net:
    """The network of an official R2D2 checkpoint, weights loaded, in eval mode."""
    path = Path(path)
    checkpoint = _read_checkpoint(path)
    arch = architecture_from_string(str(checkpoint["net"]))
    state = {re.sub(r"^module\.", "", k): v for k, v in checkpoint["state_dict"].items()}
    net = R2D2Net(arch)
    try:
        net.load_state_dict(state, strict=True)
    except RuntimeError as e:
        raise FileError(f"{path}: state_dict does not fit {arch.name}: {e}", path=str(path)) from e
    return net.eval()


@contextlib.contextmanager
def _quiet_quantization() -> Iterator[None]:
    """Silences torch's deprecation notices for ``torch.ao.quantization`` and its quantised
    tensors (the API still works in the supported torch versions; these notices are not about
    the caller's code)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\..*")
        warnings.filterwarnings("ignore", message=r".*torch\.ao\.quantization.*")
        warnings.filterwarnings("ignore", message=r".*(quantize_per|quant_min|reduce_range).*")
        yield


class _Int8Trunk(nn.Module):
    """Float32 NHWC input → float32 output of the int8 trunk (quantise, int8 layers, dequantise)."""

    def __init__(self, body: nn.Module) -> None:
        super().__init__()
        from torch.ao.quantization import QuantStub

        self.quant = QuantStub()
        self.body = body
        self.engine = ""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.engine and torch.backends.quantized.engine != self.engine:
            torch.backends.quantized.engine = self.engine
        with _quiet_quantization():
            return self.body(self.quant(x)).dequantize()


def quantize_trunk(net: R2D2Net, calibration: Iterable[torch.Tensor]) -> nn.Module:
    """The trunk of ``net`` (before the final upsampling), quantised to int8 for the CPU.

    Static post-training quantisation with ``torch.ao.quantization`` for torch's oneDNN engine
    (``x86`` where oneDNN is missing): batch norms folded first, each convolution fused with the
    ReLU after it, weights quantised per output channel (symmetric int8), activations per
    tensor (unsigned, reduced to 7 bits, 0–127) with ranges from ``calibration``:
    normalised RGB batches (B, 3, H, W) float32 on the CPU, as the extractor feeds the trunk.
    Activation ranges are the minimum and maximum seen (a histogram observer gave the same
    matching quality in ``tests/test_features_quality.py`` and costs seconds per image).
    The 7-bit activations keep every sum of two activation × weight products within 16 bits:
    CPUs without VNNI instructions add such pairs into saturating 16-bit lanes, and with 8-bit
    activations the int8 map then drifts from float32 (measured on an AVX2 machine without VNNI:
    49 % of the float32 keypoints found again within 1 px instead of 92 %, see
    ``tests/test_features.py``). With VNNI the eighth bit would be safe; it is given up on
    every CPU so that one calibration quantises the same way everywhere.
    Returns a module from that input to the float32 (B, D, h, w) map; it sets
    ``torch.backends.quantized.engine`` (process-wide) to its engine when it runs.
    """
    try:
        from torch.ao import quantization as tq
    except ImportError as e:  # pragma: no cover - torch builds without the quantisation API
        raise InputError(
            f"precision: int8 needs torch.ao.quantization, which torch {torch.__version__} lacks",
            field="precision",
        ) from e
    supported = torch.backends.quantized.supported_engines
    engine = next((e for e in ("onednn", "x86") if e in supported), None)
    if engine is None:
        raise InputError(
            f"precision: int8 needs torch's onednn or x86 quantised engine; this torch has {supported}",
            field="precision",
        )
    fused = copy.deepcopy(net)
    fused.fuse()
    assert fused._fused is not None
    layers = [op for op in fused._fused if not isinstance(op, nn.Upsample)]
    body = nn.Sequential(*layers).eval()
    pairs = [
        [str(i), str(i + 1)]
        for i in range(len(layers) - 1)
        if isinstance(layers[i], nn.Conv2d) and isinstance(layers[i + 1], nn.ReLU)
    ]
    torch.backends.quantized.engine = engine
    with _quiet_quantization():
        model = _Int8Trunk(tq.fuse_modules(body, pairs)).eval()
        model.qconfig = tq.QConfig(  # type: ignore[assignment]
            activation=tq.MinMaxObserver.with_args(dtype=torch.quint8, reduce_range=True),
            weight=tq.default_per_channel_weight_observer,
        )
        tq.prepare(model, inplace=True)
        seen = 0
        with torch.inference_mode():
            for batch in calibration:
                model(batch.float().contiguous(memory_format=torch.channels_last))
                seen += 1
        if seen == 0:
            raise InputError("calibration_images: expected at least one image", field="calibration_images")
        tq.convert(model, inplace=True)
    model.engine = engine
    return model


class R2D2(TorchExtractor):
    """R2D2 keypoints with 128-D unit-norm float32 descriptors (see the module docstring)."""

    name = "r2d2"
    descriptor_width = 128
    extra_precisions = ("int8",)

    def __init__(
        self,
        weights: str | Path,
        *,
        max_keypoints: int = 1000,
        device: str | None = "auto",
        threads: int | None = None,
        precision: str = "float32",
        scales: tuple[float, ...] = (1.0, 0.75, 0.5),
        min_size: int = 160,
        reliability_threshold: float = 0.7,
        repeatability_threshold: float = 0.7,
        merge_radius_px: int = 2,
        calibration_images: Sequence[npt.ArrayLike] | None = None,
    ) -> None:
        super().__init__(max_keypoints, device, threads, precision)
        if precision == "int8" and self.device.type != "cpu":
            raise InputError(
                f"precision: int8 runs on the CPU only (device is {self.device}); use float16 on CUDA",
                field="precision",
            )
        if calibration_images is not None and precision != "int8":
            raise InputError(
                f"calibration_images: only used with precision='int8', got precision={precision!r}",
                field="calibration_images",
            )
        if not scales or any(not (0.0 < s <= 1.0) for s in scales):
            raise InputError(f"scales: expected factors in (0, 1], got {scales}", field="scales")
        if merge_radius_px < 0:
            raise InputError(f"merge_radius_px: expected ≥ 0, got {merge_radius_px}", field="merge_radius_px")
        self.scales = tuple(sorted({float(s) for s in scales}, reverse=True))
        self.min_size = int(min_size)
        self.reliability_threshold = float(reliability_threshold)
        self.repeatability_threshold = float(repeatability_threshold)
        self.merge_radius_px = int(merge_radius_px)
        self.weights = Path(weights)
        self.net = load_checkpoint(self.weights)
        self.net.fuse()
        # NHWC lets oneDNN pick its fast convolution kernels on the CPU (4× here for the
        # dilated layers); it is also what cuDNN prefers for these channel counts.
        self.net.to(self.device, memory_format=torch.channels_last)
        self.descriptor_width = self.net.arch.dim
        weights, bias = self.net.head_weights()
        self._head_weights = (weights.cpu().numpy(), bias.cpu().numpy())
        self._mean = torch.tensor(_MEAN, device=self.device).view(1, 3, 1, 1)
        self._std = torch.tensor(_STD, device=self.device).view(1, 3, 1, 1)
        self._int8: nn.Module | None = None
        if calibration_images is not None:
            images = [check_image(im, f"calibration_images[{i}]") for i, im in enumerate(calibration_images)]
            with torch.inference_mode():
                self._int8 = quantize_trunk(self.net, (self._normalise([im]) for im in images))

    def scales_for(self, height: int, width: int) -> list[float]:
        """The pyramid scales used for an image of this size (longer side ≥ ``min_size``)."""
        chosen = [s for s in self.scales if max(height, width) * s + 1e-6 >= self.min_size]
        return chosen or [self.scales[0]]

    def _run_batch(self, images: list[npt.NDArray[np.uint8]]) -> list[Features]:
        with torch.inference_mode():
            return self._detect(self._normalise(images))

    def _normalise(self, images: list[npt.NDArray[np.uint8]]) -> torch.Tensor:
        """Grey uint8 images → the network's input: (B, 3, H, W) float32 ImageNet-normalised
        RGB (three equal channels), channels-last, on the device."""
        grey = self._to_tensor(images)
        return ((grey.expand(-1, 3, -1, -1) - self._mean) / self._std).contiguous(
            memory_format=torch.channels_last
        )

    def _trunk(self, image: torch.Tensor) -> torch.Tensor:
        """The trunk's map before the final upsampling, in the extractor's precision; with int8
        and no calibration images yet, the first image of ``image`` (the first batch seen)
        calibrates the trunk."""
        if self.precision == "int8":
            if self._int8 is None:
                self._int8 = quantize_trunk(self.net, [_calibration_input(image[:1])])
            return self._int8(image)
        with self.autocast():
            return self.net.trunk(image, upsample=False)

    def _detect(self, rgb: torch.Tensor) -> list[Features]:
        batch, _, height, width = rgb.shape
        xy: list[torch.Tensor] = []
        scores: list[torch.Tensor] = []
        descs: list[torch.Tensor] = []
        owner: list[torch.Tensor] = []
        sigmas: list[torch.Tensor] = []
        for scale in self.scales_for(height, width):
            # The fast variant pools by 2 and upsamples back: keep sizes even so the maps
            # have exactly the scaled image's size.
            m = self.net.arch.upsample
            h, w = m * round(height * scale / m), m * round(width * scale / m)
            image = rgb
            if (h, w) != (height, width):
                image = F.interpolate(rgb, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
            # Reduced precision (if asked) for the trunk only: the heads, whose outputs are
            # thresholded and compared with their neighbours, run in float32. The final
            # upsampling of the fast variant is never materialised for the descriptors, which
            # are interpolated at the keypoints only, nor on the CPU for the heads.
            low = self._trunk(image)
            rel, rep = self._heads(low, m)
            maxima = rep == window_max(rep, 1)
            maxima &= rep >= self.repeatability_threshold
            maxima &= rel >= self.reliability_threshold
            b, _, y, x = maxima.nonzero(as_tuple=True)
            offset = refine_subpixel(rep, b, y, x)
            # Pixel centres: a pixel of the scaled image covers [x, x + 1) · width / w.
            kx = (x.float() + offset[:, 0] + 0.5) * (width / w) - 0.5
            ky = (y.float() + offset[:, 1] + 0.5) * (height / h) - 0.5
            xy.append(torch.stack([kx, ky], dim=1))
            scores.append(rel[b, 0, y, x] * rep[b, 0, y, x])
            descs.append(F.normalize(_sample_upsampled(low, b, y, x, m), p=2, dim=1))
            owner.append(b)
            # A keypoint of the scaled image is located to one of its pixels: width / w of ours.
            sigmas.append(torch.full_like(kx, max(width / w, height / h)))
        all_xy, all_scores, all_desc, all_owner, all_sigma = (
            torch.cat(t) for t in (xy, scores, descs, owner, sigmas)
        )
        keep = self._merge(all_xy, all_scores, all_owner, batch, height, width)
        out = []
        for i in range(batch):
            idx = keep[all_owner[keep] == i]
            order = torch.argsort(all_scores[idx], descending=True)[: self.max_keypoints]
            idx = idx[order]
            out.append(to_features(all_xy[idx], all_scores[idx], all_desc[idx], all_sigma[idx]))
        return out

    def _heads(self, low: torch.Tensor, upsample: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Reliability and repeatability (B, 1, H, W) at full resolution from the trunk's map
        before its final upsampling.

        On the CPU one fused pass in the Rust core (``_core._r2d2_heads``: interpolation,
        square and the three dot products per pixel, the 128-channel full-resolution map never
        written); elsewhere torch's upsampling and heads.
        """
        if self.device.type == "cpu":
            if low.dtype not in (torch.float32, torch.bfloat16):
                low = low.float()
            nhwc = low.permute(0, 2, 3, 1)
            if not nhwc.is_contiguous():
                nhwc = nhwc.contiguous()
            # bfloat16 goes over as its bit patterns (numpy has no bfloat16), read in place.
            array = nhwc.view(torch.int16).numpy() if low.dtype == torch.bfloat16 else nhwc.numpy()
            weights, bias = self._head_weights
            rel, rep = _core._r2d2_heads(array, weights, bias, upsample)
            return torch.from_numpy(rel).unsqueeze(1), torch.from_numpy(rep).unsqueeze(1)
        low = low.float()
        if upsample > 1:
            low = F.interpolate(low, scale_factor=upsample, mode="bilinear", align_corners=False)
        _, rel, rep = self.net.heads(low)
        return rel, rep

    def _merge(
        self, xy: torch.Tensor, scores: torch.Tensor, owner: torch.Tensor, batch: int, height: int, width: int
    ) -> torch.Tensor:
        """Indices of the points that have the best score within ``merge_radius_px`` (Chebyshev).

        The scores are splatted onto the full-resolution grid (maximum per pixel), max-pooled
        over the radius, and a point survives when its score is that maximum: one pass, like
        the detectors' own non-maximum suppression.
        """
        all_idx = torch.arange(xy.shape[0], device=xy.device)
        if self.merge_radius_px == 0 or xy.shape[0] == 0:
            return all_idx
        col = xy[:, 0].round().long().clamp(0, width - 1)
        row = xy[:, 1].round().long().clamp(0, height - 1)
        flat = (owner * height + row) * width + col
        grid = torch.zeros(batch * height * width, device=xy.device, dtype=scores.dtype)
        grid.scatter_reduce_(0, flat, scores, reduce="amax", include_self=True)
        r = self.merge_radius_px
        pooled = window_max(grid.view(batch, 1, height, width), r).reshape(-1)
        return all_idx[scores >= pooled[flat]]

    def __repr__(self) -> str:
        return (
            f"R2D2({self.net.arch.name}, weights={str(self.weights)!r}, max_keypoints={self.max_keypoints}, "
            f"scales={self.scales}, precision={self.precision!r}, device={self.device})"
        )


#: Largest image area (pixels) the int8 trunk is calibrated on when it calibrates itself on the
#: first image: larger inputs are shrunk to it (the calibration runs the float32 network with
#: observers: ~1 min for a full 1024×1024 pair on the loaded 2-core development box).
_CALIBRATION_AREA = 640 * 480


def _calibration_input(image: torch.Tensor) -> torch.Tensor:
    """``image`` (B, 3, H, W), shrunk (antialiased, aspect kept) to at most ``_CALIBRATION_AREA``
    pixels per image."""
    height, width = image.shape[-2:]
    factor = (_CALIBRATION_AREA / (height * width)) ** 0.5
    if factor >= 1.0:
        return image
    size = (max(16, round(height * factor)), max(16, round(width * factor)))
    return F.interpolate(image, size=size, mode="bilinear", align_corners=False, antialias=True)


def _upsample_taps(i: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Source indices and weights of output indices ``i`` of a 2× bilinear upsampling of ``n``
    samples with half-pixel centres (``align_corners=False``): output 2m reads
    0.25·x[m−1] + 0.75·x[m], output 2m+1 reads 0.75·x[m] + 0.25·x[m+1], with the indices
    clamped to [0, n) (which reproduces torch's border handling)."""
    m = i // 2
    even = i % 2 == 0
    lo = torch.where(even, m - 1, m).clamp(0, n - 1)
    hi = torch.where(even, m, m + 1).clamp(0, n - 1)
    w_lo = torch.where(even, 0.25, 0.75).to(torch.float32)
    return lo, hi, w_lo, 1.0 - w_lo


def _sample_upsampled(
    low: torch.Tensor, b: torch.Tensor, y: torch.Tensor, x: torch.Tensor, upsample: int
) -> torch.Tensor:
    """Rows ``(N, D)`` float32 of ``F.interpolate(low, scale_factor=upsample, mode="bilinear")``
    at the output pixels ``(b, y, x)``, interpolated from ``low`` (B, D, h, w) at those points
    only (``upsample`` 1 or 2)."""
    if upsample == 1:
        return low[b, :, y, x].float()
    y0, y1, wy0, wy1 = _upsample_taps(y, low.shape[2])
    x0, x1, wx0, wx1 = _upsample_taps(x, low.shape[3])
    top = wx0[:, None] * low[b, :, y0, x0] + wx1[:, None] * low[b, :, y0, x1]
    bottom = wx0[:, None] * low[b, :, y1, x0] + wx1[:, None] * low[b, :, y1, x1]
    return wy0[:, None] * top + wy1[:, None] * bottom

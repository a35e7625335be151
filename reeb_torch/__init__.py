"""reeb-torch: training-free REEB object proposals for driving images, in PyTorch.

>>> from reeb_torch import ProposalGenerator
>>> gen = ProposalGenerator()              # package default config, top_k=2000
>>> out = gen(images)                      # B×3×H×W float in [0, 1] or uint8, or a list
>>> out[0]["boxes"], out[0]["scores"]      # Tensor[N, 4] (x1, y1, x2, y2), Tensor[N]
"""

from typing import TYPE_CHECKING

# every name is imported on its first use (PEP 562), not by ``import reeb_torch``: the
# settings import numba (~0.4 s), the generator torch; so the ``reeb`` command's own Ctrl-C
# handling (exit 130, one line) is in place before either loads (reeb_torch.runs.ctrl_c)
if TYPE_CHECKING:  # the same names, as type checkers read them (py.typed)
    from .config import PRESETS, ReebConfig, get_preset
    from .generator import Inspection, ProposalGenerator, propose, warmup
    from .io import ImageReadError, read_image

_LAZY = {"ReebConfig": "config", "PRESETS": "config", "get_preset": "config",
         "ProposalGenerator": "generator", "propose": "generator", "Inspection": "generator",
         "warmup": "generator", "read_image": "io", "ImageReadError": "io"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))

__all__ = [
    "ReebConfig",
    "PRESETS",
    "get_preset",
    "ProposalGenerator",
    "propose",
    "Inspection",
    "warmup",
    "read_image",
    "ImageReadError",
]
__version__ = "0.1.0"

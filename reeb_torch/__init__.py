"""reeb-torch: training-free REEB object proposals for driving images, in PyTorch.

>>> from reeb_torch import ProposalGenerator
>>> gen = ProposalGenerator()              # package default config, top_k=2000
>>> out = gen(images)                      # B×3×H×W float in [0, 1] or uint8, or a list
>>> out[0]["boxes"], out[0]["scores"]      # Tensor[N, 4] (x1, y1, x2, y2), Tensor[N]
"""

from .config import PRESETS, ReebConfig, get_preset
from .generator import Inspection, ProposalGenerator, propose, warmup
from .io import ImageReadError, read_image

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

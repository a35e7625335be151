"""REEB proposals inside torchvision two-stage detectors.

>>> from reeb_torch.detection import ReebRPN, reeb_fasterrcnn_mobilenet_v3, build_cache
>>> model = reeb_fasterrcnn_mobilenet_v3(num_classes=5)        # REEB proposals, from scratch
>>> model.rpn                                                    # a ReebRPN, attached
>>> other = torchvision.models.detection.maskrcnn_resnet50_fpn(weights=None,
...                                                             weights_backbone=None)
>>> ReebRPN().attach(other)                                      # any GeneralizedRCNN
>>> cache = build_cache(dataset, "proposals.pt")                # once per data set
>>> model = reeb_fasterrcnn_mobilenet_v3(num_classes=5, cache="proposals.pt")
"""

from .builder import load_backbone_weights, reeb_fasterrcnn_mobilenet_v3
from .cache import (
    CACHE_FORMAT,
    CACHE_VERSION,
    CacheEntry,
    ProposalCache,
    StaleCacheError,
    build_cache,
    image_digest,
)
from .rpn import ReebRPN, map_boxes

__all__ = [
    "ReebRPN",
    "map_boxes",
    "reeb_fasterrcnn_mobilenet_v3",
    "load_backbone_weights",
    "ProposalCache",
    "CacheEntry",
    "StaleCacheError",
    "build_cache",
    "image_digest",
    "CACHE_FORMAT",
    "CACHE_VERSION",
]

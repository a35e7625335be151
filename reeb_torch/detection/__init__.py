"""REEB proposals inside torchvision two-stage detectors, and a detector to train on your frames.

>>> from reeb_torch.detection import ReebDetector
>>> det = ReebDetector.fit(["my_frames/"])                      # labelled KITTI-format folders
>>> det.save("det.safetensors"); det = ReebDetector.load("det.safetensors")
>>> det([image])                 # [{"boxes": [D, 4] xyxy, "labels": [D] int64, "scores": [D]}]

The parts, for those who build their own:

>>> from reeb_torch.detection import ReebRPN, build_cache
>>> model = torchvision.models.detection.fasterrcnn_mobilenet_v3_large_fpn(
...     weights=None, weights_backbone=None, num_classes=5)
>>> ReebRPN().attach(model)                                      # any GeneralizedRCNN
>>> cache = build_cache(dataset, "proposals.pt")                # once per data set
>>> ReebRPN(cache="proposals.pt").attach(model)                 # its proposals read back

The pretrained detector (the ``detect`` extra): a frozen ImageNet EfficientNet-Lite0, its
maps cached per frame, only the heads trained:

>>> model = reeb_fasterrcnn_lite0(num_classes=4)                # Car, Pedestrian, Cyclist
>>> frames = [CachedFrame(...), ...]                             # frozen_features(model, items, cache)
>>> train_heads(model, frames); detect(model, frames)
"""

from .detector import PROPOSALS, DetectorSettings, ReebDetector, proposal_settings
from .detector_file import DetectorFileError
from .proposal_cache import (
    CACHE_FORMAT,
    CACHE_VERSION,
    CacheEntry,
    ProposalCache,
    StaleCacheError,
    build_cache,
    image_digest,
)
from .feature_cache import FeatureCache, FrameFeatures, compute_features, frozen_features
from .fitting import (
    default_cache_dir,
    detector_stats,
    evaluate_detector,
    format_paired,
    format_scores,
    paired_scores,
    scores_of,
)
from .forward import CachedFrame, drop_ignored, frame_forward
from .head_training import TrainSettings, detect, mirror_boxes, train_heads
from .kitti import KITTI_CLASSES, load_frames, mirrored, result_lines, write_results
from .lite0 import EfficientNetLite0, load_lite0, weights_digest
from .lite0_detector import reeb_fasterrcnn_lite0
from .rpn import ReebRPN, map_boxes

__all__ = [
    "ReebDetector",
    "DetectorSettings",
    "DetectorFileError",
    "PROPOSALS",
    "proposal_settings",
    "evaluate_detector",
    "detector_stats",
    "scores_of",
    "paired_scores",
    "format_scores",
    "format_paired",
    "default_cache_dir",
    "KITTI_CLASSES",
    "load_frames",
    "mirrored",
    "result_lines",
    "write_results",
    "ReebRPN",
    "map_boxes",
    "ProposalCache",
    "CacheEntry",
    "StaleCacheError",
    "build_cache",
    "image_digest",
    "CACHE_FORMAT",
    "CACHE_VERSION",
    "reeb_fasterrcnn_lite0",
    "EfficientNetLite0",
    "load_lite0",
    "weights_digest",
    "FeatureCache",
    "FrameFeatures",
    "compute_features",
    "frozen_features",
    "CachedFrame",
    "TrainSettings",
    "train_heads",
    "detect",
    "frame_forward",
    "drop_ignored",
    "mirror_boxes",
]

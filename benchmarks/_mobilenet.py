"""The MobileNetV3 detector of ``rpn_arms.py``: the same network on REEB's proposals or on a
learned RPN, trained from scratch (docs/results.md, "A MobileNetV3 detector from scratch").

The product's detector is ``reeb detector fit``'s (:class:`reeb_torch.detection.ReebDetector`);
this one is the experiment's, built on the public :class:`~reeb_torch.detection.ReebRPN`.

:func:`reeb_fasterrcnn_mobilenet_v3` builds torchvision's Faster R-CNN with a
MobileNetV3-Large + FPN backbone (as ``fasterrcnn_mobilenet_v3_large_fpn``),
:class:`~torchvision.ops.MultiScaleRoIAlign` RoI pooling, the two-layer box head and the
box predictor, and :class:`~reeb_torch.detection.ReebRPN` as its proposal stage. With
``proposals="learned"`` the same function builds the control: the identical network with
torchvision's learned :class:`~torchvision.models.detection.rpn.RegionProposalNetwork`.
Both arms are built the same way, so with the same ``torch`` seed their backbone and
heads start from the same weights.

Nothing is downloaded: backbone weights come from an optional local file, and without one
every layer is trained from scratch (BatchNorm trainable, as torchvision does).
"""

from __future__ import annotations

import os
from typing import Any, Literal

import torch
from torch import nn
from torchvision.models import mobilenet_v3_large
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.backbone_utils import _mobilenet_extractor
from torchvision.ops import misc as misc_nn_ops

from reeb_torch import ReebConfig
from reeb_torch.detection import ProposalCache, ReebRPN

__all__ = ["reeb_fasterrcnn_mobilenet_v3", "load_backbone_weights"]

# MobileNetV3-Large has 6 stages that can be frozen or trained (torchvision's count).
_MOBILENET_STAGES = 6


def load_backbone_weights(backbone: nn.Module, path: str | os.PathLike) -> None:
    """Load a local state dict of torchvision's ``mobilenet_v3_large`` into ``backbone``.

    ``path``: a file written by ``torch.save(model.state_dict())`` for a
    :func:`torchvision.models.mobilenet_v3_large` (keys ``features.*``, ``classifier.*``;
    e.g. ImageNet weights fetched once by hand), or a dict holding it under
    ``"state_dict"`` or ``"model"``. Every ``features.*`` tensor must be present and fit;
    ``classifier.*`` is ignored (a detector has no use for it).
    """
    sd = torch.load(path, map_location="cpu", weights_only=True)
    for key in ("state_dict", "model"):
        if isinstance(sd, dict) and key in sd and isinstance(sd[key], dict):
            sd = sd[key]
    if not isinstance(sd, dict):
        raise ValueError(f"{path}: not a state dict")
    features = {k: v for k, v in sd.items() if k.startswith("features.")}
    if not features:
        raise ValueError(f"{path}: no 'features.*' tensors; expected a mobilenet_v3_large state dict")
    missing, unexpected = backbone.load_state_dict(features, strict=False)
    missing = [k for k in missing if k.startswith("features.") and not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(f"{path}: does not fit mobilenet_v3_large: missing {missing[:5]}, "
                         f"unexpected {unexpected[:5]}")


def reeb_fasterrcnn_mobilenet_v3(
    num_classes: int,
    *,
    proposals: Literal["reeb", "learned"] = "reeb",
    config: ReebConfig | None = None,
    cache: ProposalCache | str | os.PathLike | None = None,
    on_miss: Literal["error", "compute"] = "error",
    backbone_weights: str | os.PathLike | None = None,
    trainable_backbone_layers: int | None = None,
    min_size: int = 320,
    max_size: int = 1088,
    top_k_train: int = 1000,
    top_k_test: int = 300,
    **kwargs: Any,
) -> FasterRCNN:
    """Faster R-CNN, MobileNetV3-Large FPN backbone, REEB (or learned) proposals.

    Args:
        num_classes: number of classes *including* the background, which is label 0
            (KITTI's four classes: ``num_classes=5``, labels ``1..4``).
        proposals: ``"reeb"``: :class:`ReebRPN`, attached to the model so REEB sees the
            input images; ``"learned"``: torchvision's RPN with its
            ``fasterrcnn_mobilenet_v3_large_fpn`` anchors (sizes 32-512, ratios
            0.5/1/2 on each of the 3 feature maps).
        config: REEB settings (``None``: ``ReebConfig()`` with ``top_k`` = the larger
            post-NMS top-N). Ignored with ``proposals="learned"``.
        cache: precomputed proposals (:class:`ProposalCache` or its file) built with
            ``config``; see :func:`reeb_torch.detection.build_cache`.
        on_miss: ``ReebRPN``'s policy for images missing from the cache.
        backbone_weights: local state dict of ``mobilenet_v3_large``
            (:func:`load_backbone_weights`); the backbone then uses frozen BatchNorm and
            trains its last ``trainable_backbone_layers`` stages (default 3 of 6). Without
            it everything is trained from scratch.
        min_size, max_size: the model transform's resize (shorter side, longest side
            bound), in pixels. KITTI's 1242×375 frames become 1060×320 by default.
        top_k_train, top_k_test: proposals per image handed to
            the box head, in training and evaluation, for either arm.
        **kwargs: passed to :class:`~torchvision.models.detection.FasterRCNN` (e.g.
            ``box_detections_per_img``, ``box_score_thresh``, ``image_mean``).

    Returns:
        A :class:`~torchvision.models.detection.FasterRCNN`: ``model(images, targets)``
        returns losses in training and, in evaluation, detections
        ``{"boxes", "labels", "scores"}`` in the pixels of the input images.
    """
    if proposals not in ("reeb", "learned"):
        raise ValueError(f"proposals must be 'reeb' or 'learned', got {proposals!r}")
    if not (isinstance(num_classes, int) and num_classes >= 2):
        raise ValueError(f"num_classes must be an int >= 2 (background included), got {num_classes!r}")
    is_trained = backbone_weights is not None
    if not is_trained:
        trainable_backbone_layers = _MOBILENET_STAGES
    elif trainable_backbone_layers is None:
        trainable_backbone_layers = 3
    norm_layer = misc_nn_ops.FrozenBatchNorm2d if is_trained else nn.BatchNorm2d

    mobilenet = mobilenet_v3_large(weights=None, norm_layer=norm_layer)
    if backbone_weights is not None:
        load_backbone_weights(mobilenet, backbone_weights)
    backbone = _mobilenet_extractor(mobilenet, True, trainable_backbone_layers)

    anchor_sizes = ((32, 64, 128, 256, 512),) * 3
    aspect_ratios = ((0.5, 1.0, 2.0),) * len(anchor_sizes)
    # Both arms build the learned RPN, so the random initialisation of the backbone and
    # heads consumes the same random numbers in both; the REEB arm then replaces it.
    model = FasterRCNN(
        backbone,
        num_classes,
        min_size=min_size,
        max_size=max_size,
        rpn_anchor_generator=AnchorGenerator(anchor_sizes, aspect_ratios),
        rpn_post_nms_top_n_train=top_k_train,
        rpn_post_nms_top_n_test=top_k_test,
        rpn_pre_nms_top_n_train=max(2000, top_k_train),
        rpn_pre_nms_top_n_test=max(1000, top_k_test),
        **kwargs,
    )
    if proposals == "reeb":
        rpn = ReebRPN(
            config,
            top_k_train=top_k_train,
            top_k_test=top_k_test,
            cache=cache,
            on_miss=on_miss,
            image_mean=model.transform.image_mean,
            image_std=model.transform.image_std,
        )
        rpn.attach(model)
    return model

"""A detector for your camera: REEB's proposals, a frozen pretrained backbone, trained heads.

>>> from reeb_torch.detection import ReebDetector
>>> det = ReebDetector.fit(["my_frames/"], epochs=12, seed=0)   # KITTI-format labelled folders
>>> det.save("det.safetensors")
>>> det = ReebDetector.load("det.safetensors")
>>> out = det([image])            # image: uint8 [3, H, W] RGB (or float in [0, 1])
>>> out[0]["boxes"], out[0]["labels"], out[0]["scores"]
>>> det.categories[int(out[0]["labels"][0])]                   # "Car"

The network is :func:`~reeb_torch.detection.reeb_fasterrcnn_lite0`: torchvision's Faster
R-CNN on the frozen ImageNet EfficientNet-Lite0 (the ``detect`` extra), with a
:class:`~reeb_torch.detection.ReebRPN` running REEB (its default settings with the learned
ranking, the ``training-free`` preset, or the default ranking with other weights). Only the
neck and the box head train (:meth:`ReebDetector.fit`, :mod:`reeb_torch.detection.fitting`);
the file (:mod:`reeb_torch.detection.detector_file`) holds them and what made them, and, where
the proposals rank with a user's weights file, that file too: it runs where that file is gone.
"""

from __future__ import annotations

import atexit
import dataclasses
import hashlib
import os
import re
import shutil
import tempfile
import typing
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import torch
from torch import Tensor, nn

from .._fields import check_fields
from ..config import ReebConfig, get_preset
from ..io import replace_file
from ..ranker import (
    SAME_IMAGE_BITS,
    SHIPPED,
    RankerWeightsError,
    frame_hash,
    hash_distance,
    load_ranker,
    resolve_ranker,
    seen_hashes,
)
from .box_head import factorise_box_head, quantise_box_head
from .detector_file import (
    DetectorFileError,
    check_tensors,
    not_a_file,
    ranker_file_bytes,
    ranker_parts,
    read_detector_file,
    trained_keys,
    write_detector_file,
)
from .inference import detect_images
from .kitti import KITTI_CLASSES
from .lite0 import native_bfloat16, weights_digest
from .lite0_detector import reeb_fasterrcnn_lite0

if TYPE_CHECKING:
    from .head_training import TrainSettings

__all__ = ["DetectorSettings", "SETTINGS_RANGES", "ReebDetector", "proposal_settings", "PROPOSALS", "PROPOSAL_FIXED",
           "SHIPPED_DETECTORS", "resolve_detector"]

PROPOSALS = ("default", "training-free")
"""The named proposal settings; a ranker weights file (``reeb fit``) is the third choice."""

SHIPPED_DETECTORS: dict[str, str] = {"kitti": "kitti.safetensors"}
"""Shipped detectors by name (``ReebDetector.load("kitti")``, ``reeb detect --detector kitti``):
files in ``reeb_torch/detection/weights/``; each file's provenance names the frames and the
command that made it (``reeb detector show kitti``)."""


def resolve_detector(spec: str | os.PathLike) -> Path:
    """The detector file ``spec`` names: a shipped name (:data:`SHIPPED_DETECTORS`) or a path
    (``~`` expanded). Whether the file exists is :func:`~reeb_torch.detection.detector_file.
    read_detector_file`'s to say."""

    if isinstance(spec, str) and spec in SHIPPED_DETECTORS:
        return Path(str(resources.files("reeb_torch.detection").joinpath("weights", SHIPPED_DETECTORS[spec])))
    return Path(os.path.expanduser(str(spec)))


BACKBONE = "efficientnet-lite0"


@dataclass(frozen=True)
class DetectorSettings:
    """The detector's shape and inference settings (stored in its file).

    Attributes:
        min_size, max_size: the input resize (shorter side; bound on the longer side).
        neck_channels: channels of the neck and the pooled RoI features.
        representation_size: units of each of the box head's two fully connected layers.
        box_head_rank: 0: the box head's first layer (``neck_channels * 49`` inputs by
            ``representation_size``, most of the file and of the head's time) in full; R: the
            trained layer replaced by its rank-R approximation once training ends
            (:func:`~reeb_torch.detection.box_head.factorise_box_head`).
        box_head_int8: the box head's layers in int8, one scale per output unit
            (:func:`~reeb_torch.detection.box_head.quantise_box_head`: a quarter of their size,
            and on the CPU an int8 product), made from the trained layers once training ends;
            ``False``: float layers (a file without this field has them).
        precision: the frozen backbone's, ``"bfloat16"`` (the default) or ``"float32"``:
            the heads are trained on the maps it gives, and detection computes them the same
            way where the device computes bfloat16 natively (otherwise in float32, with a
            warning). A file without this field was trained on float32 maps.
        crop_top: the share of the resized image's height, from the top, that the backbone
            skips (rounded down to a multiple of 32 rows; 0: none): rows where no object of
            the classes lies (``ReebDetector.fit(auto_crop=True)`` and ``reeb detector fit``
            set it from the training labels: :func:`~reeb_torch.detection.fitting.
            crop_from_labels`).
        box_passes: the box head's passes in detection: each after the first pools the boxes
            the last one regressed and averages its class scores in (training is one pass;
            an inference setting, so a file's heads run with any number).
        top_k_train, top_k_test: REEB proposals per image handed to the box head in training
            and in detection (files written with the names ``proposals_train`` and
            ``proposals_test`` load as these).
        rois: RoIs sampled per image for the box head's loss.
        score_thresh: detections below this score are dropped.
        nms_thresh: per-class NMS IoU of the detections.
        detections_per_img: at most this many detections per image.
    """

    min_size: int = 576
    max_size: int = 2048
    neck_channels: int = 128
    representation_size: int = 1024
    box_head_rank: int = 0
    box_head_int8: bool = True
    precision: Literal["float32", "bfloat16"] = "bfloat16"
    crop_top: float = 0.0
    box_passes: int = 2
    top_k_train: int = 2000
    top_k_test: int = 1000
    rois: int = 256
    score_thresh: float = 0.01
    nms_thresh: float = 0.5
    detections_per_img: int = 100

    def __post_init__(self) -> None:
        for name, value in _checked_settings("DetectorSettings", dataclasses.asdict(self)).items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, d: Any, owner: str = "DetectorSettings") -> DetectorSettings:
        """The settings of a dict of fields (as a detector file stores them; a field missing
        takes its default), every value checked for its type and range before anything is
        built (:data:`SETTINGS_RANGES`).

        Raises:
            TypeError: not a dict, or a value of the wrong type; ValueError: an unknown field,
            or a value out of its range. Each names ``<owner>.<field>``.
        """
        if not isinstance(d, dict):
            raise TypeError(f"{owner} must be an object of DetectorSettings fields, got {type(d).__name__}")
        d = {_FORMER_NAMES.get(k, k): v for k, v in d.items()}
        unknown = sorted(set(d) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"{owner} has fields this version does not know: {', '.join(map(str, unknown))}")
        return cls(**_checked_settings(owner, {"precision": "float32", "box_head_int8": False, **d}))


_FORMER_NAMES = {"proposals_train": "top_k_train", "proposals_test": "top_k_test"}
"""Fields that files written before the number of proposals had one name store by another."""

SETTINGS_RANGES: dict[str, str | None] = {
    "min_size": "[32, 4096]",
    "max_size": "[32, 8192]",
    "neck_channels": "[1, 1024]",
    "representation_size": "[1, 8192]",
    "box_head_rank": "[0, 8192]",
    "box_head_int8": None,
    "precision": None,
    "crop_top": "[0, 0.9]",
    "box_passes": "[1, 4]",
    "top_k_train": "[1, 20000]",
    "top_k_test": "[1, 20000]",
    "rois": "[1, 4096]",
    "score_thresh": "[0, 1]",
    "nms_thresh": "[0, 1]",
    "detections_per_img": "[1, 10000]",
}
"""The range of each :class:`DetectorSettings` field (its type is its annotation's): what a
detector file's settings are checked against before a network is built. A new field needs
its entry here: an interval (``"[1, 1024]"``, ``"(0, 1]"``, ``">= 1"``), or None where its
type says all (a bool, a ``Literal`` of words). Sizes in pixels; the bounds keep a tampered
file from asking for memory no machine has."""


def _checked_settings(owner: str, values: dict[str, Any]) -> dict[str, Any]:
    return check_fields(owner, values, typing.get_type_hints(DetectorSettings), SETTINGS_RANGES)


PROPOSAL_FIXED = {"top_k": "the detector's proposals per image (DetectorSettings.top_k_train/_test)",
                  "ranker": "the proposals' name or ranker weights file"}
"""The REEB fields a detector sets itself, which ``changes`` may not: field -> what sets it."""


def proposal_settings(spec: str, top_k: int,
                      changes: Mapping[str, Any] | None = None) -> tuple[ReebConfig, dict[str, Any]]:
    """REEB's settings for ``spec`` and what names them in a detector file.

    Args:
        spec: ``"default"`` (the learned ranking, shipped weights), ``"training-free"``, or
            the path of ranker weights (``reeb fit``) used with the default settings.
        top_k: proposals REEB keeps per image.
        changes: other values of :class:`~reeb_torch.ReebConfig` fields (``{"class_quota":
            {"Pedestrian": 0.2}}``), applied over ``spec``'s; not ``top_k`` or ``ranker``
            (:data:`PROPOSAL_FIXED`).

    Returns:
        ``(config, info)``; ``info``: ``{"spec", "config", "fingerprint", "ranker_sha256"}``.

    Raises:
        ValueError: an unknown name and no such file, a field ``changes`` may not set, or a
            value ReebConfig refuses (one line).
    """
    config = _proposal_config(spec, top_k, changes)
    return config, _proposal_info(spec, config, _ranker_file(config)[0])


def _proposal_config(spec: str, top_k: int, changes: Mapping[str, Any] | None = None) -> ReebConfig:
    fixed = sorted(set(changes or ()) & set(PROPOSAL_FIXED))
    if fixed:
        raise ValueError(f"REEB's {fixed[0]} is {PROPOSAL_FIXED[fixed[0]]}: it cannot be changed on its own")

    if spec in PROPOSALS:
        config = get_preset(spec)
    elif Path(os.path.expanduser(spec)).is_file():
        config = get_preset("default").replace(ranker=str(Path(os.path.expanduser(spec)).resolve()))
    else:
        raise ValueError(f"proposals {spec!r}: expected {' or '.join(PROPOSALS)} or a ranker weights file "
                         f"(reeb fit's .safetensors); {not_a_file(Path(os.path.expanduser(spec))) or 'no such file'}")
    if changes:  # as a file gives them (lists for tuples), each checked and named when refused
        return ReebConfig.from_dict({**config.to_dict(), **changes, "top_k": int(top_k)})
    return config.replace(top_k=int(top_k))


def _proposal_info(spec: str | None, config: ReebConfig, ranker_sha: str | None) -> dict[str, Any]:
    return {"spec": spec, "config": config.to_dict(), "fingerprint": config.fingerprint(),
            "ranker_sha256": ranker_sha}


def _ranker_file(config: ReebConfig) -> tuple[str | None, bytes | None]:
    """The SHA-256 of ``config.ranker``'s weights file (None without a ranker) and, for a
    user's file (not a shipped name), its bytes: what a saved detector embeds. A file laid
    out otherwise than safetensors writes it (another tool's) is not embedded, with a warning:
    the embedded copy would not have its SHA-256."""
    if config.ranker == "none":
        return None, None

    data = resolve_ranker(config.ranker).read_bytes()
    sha = hashlib.sha256(data).hexdigest()
    if config.ranker in SHIPPED:
        return sha, None
    try:
        same = ranker_file_bytes(*ranker_parts(data)) == data
    except ValueError:  # not safetensors: the ranker's loader refuses it, in one line
        return sha, None
    if not same:
        warnings.warn(f"ranker weights {config.ranker!r} are not laid out as reeb fit writes them: a saved detector "
                      "names the file by its path instead of holding a copy (rewrite it with reeb fit)", stacklevel=3)
        return sha, None
    return sha, data


def _check_image(image: Tensor) -> None:
    if not isinstance(image, Tensor) or image.dim() != 3 or image.shape[0] != 3:
        raise ValueError("ReebDetector expects RGB images [3, H, W], got "
                         f"{tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__}")
    if image.dtype != torch.uint8 and not image.is_floating_point():
        raise ValueError(f"ReebDetector expects uint8 or float images in [0, 1], got {image.dtype}")


def _runnable_precision(precision: str, device: str | torch.device) -> str:
    """``precision`` where ``device`` computes it natively; ``float32`` (with a warning
    saying so) where a ``bfloat16`` detector meets a device that would only emulate it."""

    if precision == "bfloat16" and not native_bfloat16(device):
        warnings.warn(f"this {torch.device(device).type.upper()} has no native bfloat16: the detector's backbone "
                      "runs in float32 instead (its heads were trained on bfloat16 maps; detections may differ "
                      "slightly)", stacklevel=3)
        return "float32"
    return precision


class ReebDetector(nn.Module):
    """Faster R-CNN with REEB's proposals for ``classes`` (see the module doc).

    Args:
        classes: the class names, labels 1..C (0 is the background); KITTI's by default.
        proposals: ``"default"``, ``"training-free"`` or a ranker weights file
            (:func:`proposal_settings`).
        settings: the network's shape and inference settings.
        config: REEB's settings, instead of ``proposals`` (as a file restores them).
        weights: the EfficientNet-Lite0 state dict (default: the ``detect`` extra's).
        device: where it will run: a ``bfloat16`` detector runs its backbone in ``float32``
            on a device without native bfloat16 (:func:`~reeb_torch.detection.lite0.
            native_bfloat16`), with a warning; :attr:`precision` is what runs.

    ``forward(images)``: a list of ``[3, H, W]`` RGB images (uint8, or float in [0, 1]; sizes
    may differ) -> one dict per image: ``boxes`` ``float32 [D, 4]`` xyxy input pixels,
    ``labels`` ``int64 [D]`` (indices into :attr:`categories`), ``scores`` ``float32 [D]``,
    best first. Always in evaluation mode, without gradients.

    Safe to call from several threads. The backbone's maps depend on torch's thread count
    (its kernels split their sums by thread, and in ``bfloat16`` that shows), so scores from
    threads sharing the process's threads may differ from a serial run's in their third
    decimal; the proposals do not.
    """

    def __init__(self, classes: Sequence[str] = KITTI_CLASSES, proposals: str = "default",
                 settings: DetectorSettings = DetectorSettings(), *, config: ReebConfig | None = None,
                 weights: str | os.PathLike | None = None, device: str | torch.device = "cpu") -> None:
        super().__init__()

        if isinstance(classes, str) or not classes or len(set(classes)) != len(classes):
            raise ValueError(f"classes must be distinct names, at least one; got {classes!r}")
        self.classes: tuple[str, ...] = tuple(str(c) for c in classes)
        self.categories: tuple[str, ...] = ("__background__", *self.classes)
        self.settings = settings
        top_k = max(settings.top_k_train, settings.top_k_test)
        if config is None:
            config = _proposal_config(proposals, top_k)
        sha, self._ranker_bytes = _ranker_file(config)
        self.proposals = _proposal_info(proposals, config, sha)
        self.backbone_sha256 = weights_digest(weights)
        s = settings
        self.precision = _runnable_precision(s.precision, device)
        self.model = reeb_fasterrcnn_lite0(
            len(self.categories), proposals="reeb", config=config, weights=weights,
            min_size=s.min_size, max_size=s.max_size, neck_channels=s.neck_channels,
            representation_size=s.representation_size, box_head_rank=s.box_head_rank,
            box_head_int8=s.box_head_int8, precision=self.precision,
            top_k_train=s.top_k_train, top_k_test=s.top_k_test,
            box_batch_size_per_image=s.rois, box_score_thresh=s.score_thresh, box_nms_thresh=s.nms_thresh,
            box_detections_per_img=s.detections_per_img)
        self.meta: dict[str, Any] = {}
        """``{"provenance": {...}}``: the frames and command that trained it (from its file)."""
        self.clock: Any = None
        """A :class:`~reeb_torch.detection.inference.StageClock` that :meth:`forward` times
        its stages on, or ``None`` (the default: no timing)."""
        self.eval()

    @property
    def config(self) -> ReebConfig:
        """REEB's settings of the proposals. Loaded from a file that embeds its ranker,
        ``config.ranker`` is the private copy it was unpacked to (``proposals["config"]``
        records the file it was fitted with)."""
        return self.model.rpn.config

    @property
    def ranker_embedded(self) -> bool:
        """Whether :meth:`save` puts the proposals' ranker weights in the file: a user's
        weights file, not a shipped name nor ``ranker='none'``."""
        return self._ranker_bytes is not None

    def forward(self, images: Sequence[Tensor]) -> list[dict[str, Tensor]]:
        """Detections of each image, in evaluation mode.

        The stages, as :func:`~reeb_torch.detection.inference.detect_images` runs them:
        REEB's proposals of every image (``model.rpn``, a :class:`ReebRPN`) → per group of
        images of one size, the resize, the top rows cut (``settings.crop_top``) and the
        frozen backbone → per image, the neck, RoI pooling, the box head's passes
        (``settings.box_passes``) and the postprocess back to input pixels.

        Args:
            images: ``[3, H, W]`` RGB each, uint8 or float in [0, 1], on the detector's
                device; sizes may differ. A ``[B, 3, H, W]`` tensor is taken as B images.

        Returns:
            One dict per image: ``boxes`` ``float32 [D, 4]`` xyxy input pixels, ``labels``
            ``int64 [D]`` (indices into :attr:`categories`), ``scores`` ``float32 [D]``, best
            first.
        """
        if isinstance(images, Tensor) and images.dim() == 4:
            images = list(images)
        if not isinstance(images, (list, tuple)):
            raise TypeError(f"ReebDetector expects a list of images [3, H, W] or a (B, 3, H, W) tensor, got "
                            f"{type(images).__name__}")
        for im in images:
            _check_image(im)
        return detect_images(self.model, list(images), self.settings.crop_top, self.clock, self.settings.box_passes)

    def factorise_box_head(self, rank: int) -> "ReebDetector":
        """Replace the trained box head's first layer by its rank-``rank`` approximation, in
        place (:func:`~reeb_torch.detection.box_head.factorise_box_head`): a smaller file
        and a faster head, with detections close to the full layer's; ``settings.box_head_rank``
        records it. Returns ``self``.

        Raises:
            ValueError: ``rank`` below 1, or the layer is factorised or in int8 already.
        """

        if rank < 1:
            raise ValueError(f"rank must be at least 1, got {rank}")
        factorise_box_head(self.model, rank)
        fc6 = self.model.roi_heads.box_head.fc6
        self.settings = dataclasses.replace(self.settings, box_head_rank=getattr(fc6, "rank", 0))
        return self

    def quantise_box_head(self) -> "ReebDetector":
        """The box head's layers in int8, in place (:func:`~reeb_torch.detection.box_head.
        quantise_box_head`): a quarter of their size in the file, and on the CPU torch's
        int8 kernels; ``settings.box_head_int8`` records it. Returns ``self``."""

        quantise_box_head(self.model)
        self.settings = dataclasses.replace(self.settings, box_head_int8=True)
        return self

    # -- file -------------------------------------------------------------------------------
    def metadata(self) -> dict[str, Any]:
        """What the file records beside the tensors (:mod:`~reeb_torch.detection.detector_file`)."""
        proposals = {**self.proposals, "ranker_embedded": True} if self.ranker_embedded else self.proposals
        return {"classes": list(self.classes), "settings": dataclasses.asdict(self.settings),
                "backbone": {"name": BACKBONE, "sha256": self.backbone_sha256},
                "proposals": proposals, "provenance": self.meta.get("provenance", {})}

    def save(self, path: str | os.PathLike) -> Path:
        """Write the trained tensors and :meth:`metadata` to ``path`` (safetensors, atomically),
        with the proposals' ranker weights file where it is a user's (:attr:`ranker_embedded`)."""
        return write_detector_file(path, trained_keys(self.model.state_dict()), self.metadata(), self._ranker_bytes)

    @classmethod
    def load(cls, path: str | os.PathLike, device: str | torch.device = "cpu") -> ReebDetector:
        """The detector a :meth:`save` wrote (a path, or a shipped name such as ``"kitti"``:
        :data:`SHIPPED_DETECTORS`), in evaluation mode on ``device``.

        A file that embeds its ranker runs on that copy (the file it was fitted with may be
        gone), checked against the SHA-256 recorded for it and by the ranker's own loader; a
        file without one finds the ranker where it was fitted (a warning where that file's
        SHA-256 is not the one recorded).

        Raises:
            DetectorFileError: a missing, damaged or foreign file, settings of the wrong type
                or out of range (:data:`SETTINGS_RANGES`, checked before anything is built),
                one made on other backbone weights or with proposal settings this
                installation cannot run, whose embedded ranker is damaged or whose ranker file
                is gone or unreadable; one line naming the file and what is wrong.
            ImportError: the ``detect`` extra is missing (one line naming it).
        """

        p = resolve_detector(path)
        tensors, meta, ranker = read_detector_file(p)
        try:
            settings = DetectorSettings.from_dict(meta["settings"], owner="settings")
        except (TypeError, ValueError) as e:
            raise DetectorFileError(f"detector {p}: its {e}") from None
        here = weights_digest()
        if meta["backbone"].get("sha256") != here or meta["backbone"].get("name") != BACKBONE:
            raise DetectorFileError(f"detector {p}: trained on other backbone weights ({meta['backbone']}); this "
                                    f"installation has {BACKBONE} {here[:16]}... (the 'detect' extra)")
        config = _stored_config(p, meta["proposals"], ranker)
        try:
            det = cls(meta["classes"], meta["proposals"].get("spec"), settings, config=config, device=device)
        except RankerWeightsError as e:  # the file it names by its path, replaced since
            reason = re.sub(r"^ranker weights '.*?' \(.*?\):? (are |is )?", "", str(e).splitlines()[0])
            raise DetectorFileError(f"detector {p}: its proposals rank with {config.ranker!r}, which cannot be used "
                                    f"({reason})") from None
        if ranker is not None:  # its copy, checked: what the file records, not where it was unpacked
            det.proposals = {k: v for k, v in meta["proposals"].items() if k != "ranker_embedded"}
        elif meta["proposals"].get("ranker_sha256") != det.proposals["ranker_sha256"]:
            warnings.warn(f"detector {p}: its proposals were ranked with other weights than {config.ranker!r} "
                          "has here; detections may differ from those it was trained for", stacklevel=2)
        check_tensors(p, tensors, trained_keys(det.model.state_dict()))
        det.model.load_state_dict(tensors, strict=False)
        provenance = meta.get("provenance")
        det.meta = {"provenance": provenance if isinstance(provenance, dict) else {}}
        return det.to(device).eval()

    def trained_on(self, images: Sequence[Tensor]) -> list[str | None]:
        """For each image (``[3, H, W]``), the training frame that shows the same picture
        (``"folder/id"``, by :func:`reeb_torch.ranker.frame_hash` within
        :data:`~reeb_torch.ranker.SAME_IMAGE_BITS`), or ``None``: where a score measured with
        this detector is in-sample. All ``None`` for a detector without frame hashes."""

        known = seen_hashes(self.meta.get("provenance", {}))
        out: list[str | None] = []
        for image in images:
            h = frame_hash(image)
            near = [(hash_distance(h, v), k) for k, v in known.items()]
            best = min(near, default=(SAME_IMAGE_BITS + 1, None))
            out.append(best[1] if best[0] <= SAME_IMAGE_BITS else None)
        return out

    # -- training ---------------------------------------------------------------------------
    @classmethod
    def fit(cls, folders: Sequence[str | os.PathLike], *, classes: Sequence[str] = KITTI_CLASSES,
            proposals: str = "default", epochs: int = 12, seed: int = 0,
            settings: DetectorSettings = DetectorSettings(), training: TrainSettings | None = None,
            cache_dir: str | os.PathLike | None = None, limit: int | None = None, hflip: bool = False,
            auto_crop: bool = False, progress: bool = True, command: str | None = None,
            checkpoints: str | os.PathLike | None = None, frames_by: Any = None,
            proposal_changes: Mapping[str, Any] | None = None) -> ReebDetector:
        """Train a detector on labelled KITTI-format ``folders`` (:func:`~reeb_torch.
        detection.fitting.fit_detector`: the backbone's maps and REEB's proposals cached
        per frame under ``cache_dir``, the heads trained for ``epochs`` with ``seed``);
        deterministic for a seed. ``training`` overrides the optimiser's settings
        (its ``epochs``, ``seed`` and ``hflip`` are these arguments'); ``auto_crop``: the
        settings' ``crop_top`` from the training labels instead (:func:`~reeb_torch.
        detection.fitting.crop_from_labels`). ``checkpoints``: a folder where the training's
        state is kept after each epoch, so the same call after a kill goes on from it.
        ``frames_by``: the per-frame pass done elsewhere (:func:`~reeb_torch.detection.
        fitting.stored_frames`; ``reeb detector fit --engine ray``). ``proposal_changes``: REEB
        fields set over ``proposals``' settings (:func:`proposal_settings`' ``changes``;
        ``reeb detector fit --set``), kept in the file."""
        from .fitting import fit_detector
        from .head_training import TrainSettings

        base = training or TrainSettings()
        train = dataclasses.replace(base, epochs=epochs, seed=seed, hflip=hflip)
        top_k = max(settings.top_k_train, settings.top_k_test)
        config = _proposal_config(proposals, top_k, proposal_changes) if proposal_changes else None
        return fit_detector(cls, folders, classes=classes, proposals=proposals, settings=settings, training=train,
                            cache_dir=cache_dir, limit=limit, auto_crop=auto_crop, progress=progress,
                            command=command, checkpoints=checkpoints, frames_by=frames_by, config=config)

    def extra_repr(self) -> str:
        return f"classes={self.classes}, proposals={self.proposals['spec']!r}, settings={self.settings}"


def _stored_config(path: Path, info: dict[str, Any], ranker: bytes | None) -> ReebConfig:
    """REEB's settings a detector file records, with ``config.ranker`` the unpacked copy of
    the ``ranker`` it embeds (:func:`_embedded_ranker`); one line when this installation
    cannot run them."""

    try:
        config = ReebConfig.from_dict(info["config"])
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        raise DetectorFileError(f"detector {path}: proposal settings this version cannot use ({reason})") from None
    embedded = info.get("ranker_embedded") is True and config.ranker != "none"
    if embedded != (ranker is not None):
        raise DetectorFileError(f"detector {path}: " + (
            "its metadata says it holds its proposals' ranker, but it holds none" if embedded else
            "it holds ranker weights its metadata does not name (proposals_ranker.*)"))
    if ranker is not None:
        return config.replace(ranker=_embedded_ranker(path, info, ranker))
    if config.ranker != "none":
        try:
            resolve_ranker(config.ranker)
        except RankerWeightsError:
            raise DetectorFileError(f"detector {path}: its proposals rank with {config.ranker!r}, which is not "
                                    "here; put that weights file back where it was") from None
    return config


_UNPACKED: list[Path] = []
"""The private folder (made once per process, removed at its exit) embedded rankers are
unpacked to."""


def _unpack_folder() -> Path:
    if not (_UNPACKED and _UNPACKED[0].is_dir()):
        folder, pid = Path(tempfile.mkdtemp(prefix="reeb-detector-rankers-")), os.getpid()

        def remove() -> None:  # in this process only, not in a forked child
            if os.getpid() == pid:
                shutil.rmtree(folder, ignore_errors=True)

        atexit.register(remove)
        _UNPACKED[:] = [folder]
    return _UNPACKED[0]


def _embedded_ranker(path: Path, info: dict[str, Any], data: bytes) -> str:
    """The weights file of the ranker the detector file ``path`` embeds (``data``): its SHA-256
    checked against the recorded ``ranker_sha256``, unpacked to a private folder, and read by
    the ranker's checked loader (:func:`~reeb_torch.ranker.load_ranker`), each refusal one line."""

    sha, recorded = hashlib.sha256(data).hexdigest(), str(info.get("ranker_sha256"))
    if sha != recorded:
        raise DetectorFileError(f"detector {path}: its embedded proposals ranker is damaged (SHA-256 {sha[:16]}..., "
                                f"recorded {recorded[:16]}...)")
    file = _unpack_folder() / f"{sha}.safetensors"
    if not (file.is_file() and file.read_bytes() == data):
        replace_file(file, data)
    try:
        load_ranker(str(file))
    except RankerWeightsError as e:
        reason = str(e).splitlines()[0].removeprefix(f"ranker weights {str(file)!r} ({file})")
        raise DetectorFileError(f"detector {path}: its embedded proposals ranker weights{reason}") from None
    return str(file)

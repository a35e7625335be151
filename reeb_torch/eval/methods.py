"""The rows of the paper's Table 3 and what to measure: the methods, the grid, the options.

Rows are methods, columns are recall at IoU 0.3 / 0.5 / 0.7 (:data:`IOUS`) for the top 100 /
300 / 500 / 1000 / 2000 proposals (:data:`KS`; the paper's Table 3 has 500 / 1000 / 2000, the
text tables show IoU 0.5 / 0.7 alone at 100 / 300: :data:`TEXT_GRID`). Methods
(:data:`METHODS`, keys in brackets):

- BING [bing], Selective Search [selective-search], Edge Boxes [edgeboxes]: OpenCV contrib,
  see :mod:`reeb_torch.eval.baselines` (BING needs its model folder, ``bing_model``);
- Ours* [reeb-default-no-regions], Ours** [reeb-training-free]: REEB without a learned part
  (the ``training-free`` preset), without / with region enhancement;
- Ours** + learned ranking [reeb-default]: the package default, REEB's windows ordered by the
  shipped model (``ranker='kitti'``; fitted on the 106 dev frames, so on those frames its row
  is no estimate: ``reeb fit`` cross-validates it);
- Ours** + learned ranking, whole drives held out [reeb-default-wd, with ``cross_validate=FOLDS``
  and ``whole_drives``]: the default with, for each block of frames, a ranking fitted on the
  other blocks less every frame of the block's drives (``reeb fit --whole-drives``'s models):
  the estimate for drives no model saw, the one to read first;
- Ours** + learned ranking, cross-validated [reeb-default-cv, with ``cross_validate=FOLDS``]:
  the default with, for each block of frames, a ranking fitted on the other blocks of the
  frames measured (``reeb fit``'s folds, options and seed: no drive neighbour of a block on
  the training side): an estimate on labelled frames the shipped model saw; the other rows are
  then paired with ``training-free`` (the default's own row is in sample there);
- Ours** + learned ranking, fitted on the other folders [reeb-default-lofo, with
  ``leave_folder_out``]: the same with one block per data folder (another drive, another
  camera set-up): how a model holds on frames unlike those it was fitted on;
- REEB as printed [reeb-paper-no-regions, reeb-paper]: the ``paper`` preset, without / with
  region enhancement;
- REEB with your settings [reeb-config, with ``config``]: a :class:`~reeb_torch.ReebConfig` of
  the caller's (``reeb eval --config FILE --set FIELD=VALUE``: a camera file of ``reeb
  calibrate``, weights of ``reeb fit``), run as ``reeb propose`` runs it.

This module imports neither torch nor OpenCV (a method's model is built when it runs), so
the command line can list the methods and check its options at once.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..datasets.folders import FrameRange

__all__ = [
    "KS",
    "IOUS",
    "HEADLINE",
    "TEXT_GRID",
    "CROSS_VALIDATED",
    "WHOLE_DRIVES",
    "LEAVE_FOLDER_OUT",
    "CONFIGURED",
    "Table3Error",
    "Method",
    "METHODS",
    "DEFAULT_METHODS",
    "Table3Options",
]

KS = (100, 300, 500, 1000, 2000)
IOUS = (0.3, 0.5, 0.7)
TEXT_GRID: tuple[tuple[int, tuple[float, ...]], ...] = tuple((k, IOUS[1:] if k < 500 else IOUS) for k in KS)
"""The columns of the text tables, ``(k, IoUs)``: IoU 0.5 and 0.7 alone at 100 and 300
proposals (the JSON and CSV hold every k x IoU of :data:`KS` x :data:`IOUS`)."""
HEADLINE = (2000, 0.7)
"""``(k, IoU)`` of the headline, its interval and the per-class table."""
CROSS_VALIDATED = "reeb-default-cv"
"""The key of the cross-validated row (``cross_validate``; not a ``methods`` choice)."""
WHOLE_DRIVES = "reeb-default-wd"
"""The key of the cross-validated row with every frame of a held-out block's drives off the
training side (``cross_validate`` and ``whole_drives``)."""
LEAVE_FOLDER_OUT = "reeb-default-lofo"
"""The key of the row ranked by models fitted on the other folders (``leave_folder_out``)."""
CONFIGURED = "reeb-config"
"""The key of the row with the caller's settings (``config``; not a ``methods`` choice)."""


class Table3Error(ValueError):
    """Options or data with which the table cannot be computed (a one-line message: the
    command exits 2 with it)."""


@dataclass(frozen=True)
class Method:
    """One row of the table."""

    key: str
    label: str
    build: Callable[..., Callable[..., dict]]
    """``build(top_k, **options)`` -> a callable on one uint8 (3, H, W) image."""
    batched: bool = False
    """Accepts a list of images (REEB), so batch timing applies."""
    preset: str | None = None
    """The REEB preset of a REEB row, the region enhancement aside (its ranking model, if any,
    is checked against the frames)."""
    cross_validated: bool = False
    """Ranked by models fitted on the measured frames' other blocks (``cross_validate``):
    its boxes come from :func:`cross_validated_boxes`, not from ``build``."""


def _on(gen: Any, device: str | None) -> Callable:
    """``gen`` (a :class:`~reeb_torch.ProposalGenerator`) run on ``device``: the images are
    moved there (None or ``cpu``: as they are)."""
    if device is None or device == "cpu":
        return gen
    gen.to(device)
    return lambda images: gen([im.to(device) for im in images])


def _reeb(preset: str, **changes: Any) -> Callable[..., Callable]:
    """The generator of a REEB row: the preset with ``changes`` (``use_regions=False``: the
    rows without the region enhancement), on ``device``."""
    def build(top_k: int, device: str | None = None, **_: Any) -> Callable:
        from .. import ProposalGenerator, get_preset

        gen = ProposalGenerator(get_preset(preset).replace(**changes), top_k=top_k)
        gen.eval()
        return _on(gen, device)

    return build


def _configured(top_k: int, config: Any = None, device: str | None = None, **_: Any) -> Callable:
    """The generator of the row with the caller's settings (``config``), on ``device``."""
    from .. import ProposalGenerator

    gen = ProposalGenerator(config, top_k=top_k)
    gen.eval()
    return _on(gen, device)


def _baseline(name: str) -> Callable[..., Callable]:
    def build(top_k: int, bing_model: str | os.PathLike | None = None, **_: Any) -> Callable:
        from .baselines import BASELINES

        if name != "bing":
            return BASELINES[name](top_k=top_k)
        if bing_model is None:
            raise FileNotFoundError("no BING model folder given (--bing-model DIR: the folder of its nine "
                                    "ObjNessB2W8*.yml.gz files, from opencv_contrib's "
                                    "modules/saliency/samples/ObjectnessTrainedModel)")
        return BASELINES[name](top_k=top_k, model_dir=bing_model)

    return build


METHODS: dict[str, Method] = {
    m.key: m
    for m in [
        Method("bing", "BING", _baseline("bing")),
        Method("selective-search", "Selective Search", _baseline("selective-search")),
        Method("edgeboxes", "Edge Boxes (Sobel)", _baseline("edgeboxes")),
        Method("reeb-default-no-regions", "Ours* (training-free, no regions)",
               _reeb("training-free", use_regions=False), True, "training-free"),
        Method("reeb-training-free", "Ours** (training-free)", _reeb("training-free"), True, "training-free"),
        Method("reeb-default", "Ours** + learned ranking (default)", _reeb("default"), True, "default"),
        Method(WHOLE_DRIVES, "Ours** + learned ranking (whole drives held out)", _reeb("default"), True,
               cross_validated=True),
        Method(CROSS_VALIDATED, "Ours** + learned ranking (cross-validated)", _reeb("default"), True,
               cross_validated=True),
        Method(LEAVE_FOLDER_OUT, "Ours** + learned ranking (fitted on the other folders)", _reeb("default"), True,
               cross_validated=True),
        Method("reeb-paper-no-regions", "REEB paper preset, no regions", _reeb("paper", use_regions=False), True,
               "paper"),
        Method("reeb-paper", "REEB paper preset", _reeb("paper"), True, "paper"),
        Method(CONFIGURED, "REEB with your settings (--config / --set)", _configured, True),
    ]
}

DEFAULT_METHODS: tuple[str, ...] = tuple(k for k, m in METHODS.items() if not m.cross_validated and k != CONFIGURED)
"""The methods one can choose (``methods``), in table order; all of them by default."""


@dataclass(frozen=True)
class Table3Options:
    """What to measure. Checked when made (:class:`Table3Error`, a one-line message).

    Attributes:
        data: KITTI-format folders (``images/`` + ``labels/``, or ``image_2/`` + ``label_2/``);
            with several, every table is given for each folder and for all together.
        limit: only the first N frames of each folder (after ``frames``).
        frames: only frames whose numeric id lies in one of these ranges; with two or more,
            every table is also given for each range.
        methods: the rows (keys of :data:`METHODS`), in table order.
        top_k: proposals kept per image (at least 2000, Table 3's largest column).
        batch: REEB is also timed in batches of this many images (0 or 1: not).
        exclude_fitted: leave out the frames a learned ranking among the methods was fitted on
            (the same pictures, whatever their names: :func:`reeb_torch.ranker.fitted_frames`).
        cross_validate: also the default ranked, on each of this many blocks of frames, by a
            model fitted on the other blocks (0: not; else at least 2).
        whole_drives: with ``cross_validate``, also the default ranked on each block by a model
            fitted on the other blocks less every frame of the block's drives (``reeb fit
            --whole-drives``), in a row before the cross-validated one.
        leave_folder_out: also the default ranked, on each data folder, by a model fitted on
            the other folders (needs two or more folders).
        bing_model: BING's model folder (its nine ``ObjNessB2W8*.yml.gz`` files); without one
            the BING row is skipped, with a note.
        config: the caller's settings (a :class:`~reeb_torch.ReebConfig`): a row of its own
            (:data:`CONFIGURED`), after ``methods``.
        device: where the REEB rows run (``cpu``, ``cuda``, ``cuda:N``; None: the CPU).
    """

    data: Sequence[str | os.PathLike]
    limit: int | None = None
    frames: Sequence[FrameRange] = ()
    methods: Sequence[str] = DEFAULT_METHODS
    top_k: int = max(KS)
    batch: int = 8
    exclude_fitted: bool = False
    cross_validate: int = 0
    leave_folder_out: bool = False
    whole_drives: bool = False
    bing_model: str | os.PathLike | None = None
    config: Any = None
    device: str | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalise once, here
        set_(self, "data", tuple(Path(d) for d in self.data))
        set_(self, "frames", tuple(self.frames))
        set_(self, "methods", tuple(self.methods))
        if self.bing_model is not None:
            set_(self, "bing_model", Path(self.bing_model))
        if not self.data:
            raise Table3Error("no data folder given")
        unknown = [m for m in self.methods if m not in DEFAULT_METHODS]
        if unknown:
            raise Table3Error(f"unknown method {unknown[0]!r}; choose from {', '.join(DEFAULT_METHODS)}")
        if self.top_k < max(KS):
            raise Table3Error(f"--top-k must be at least {max(KS)} for Table 3's columns, got {self.top_k}")
        if self.limit is not None and self.limit < 1:
            raise Table3Error(f"--limit must be >= 1, got {self.limit}")
        if self.batch < 0:
            raise Table3Error(f"--batch must be >= 0, got {self.batch}")
        if self.cross_validate and self.cross_validate < 2:
            raise Table3Error(f"--cross-validate needs at least 2 folds, got {self.cross_validate}")
        if self.whole_drives and not self.cross_validate:
            raise Table3Error("--whole-drives needs --cross-validate FOLDS (the blocks it holds out)")
        if self.leave_folder_out and len(self.data) < 2:
            raise Table3Error("--leave-folder-out needs two or more --data folders")

    @property
    def rows(self) -> tuple[str, ...]:
        """The rows run, in table order: :attr:`methods` with the held-out rows
        (``whole_drives``, ``cross_validate``, ``leave_folder_out``) after the default's own."""
        held_out = [k for k, on in ((WHOLE_DRIVES, self.whole_drives), (CROSS_VALIDATED, self.cross_validate),
                                    (LEAVE_FOLDER_OUT, self.leave_folder_out)) if on]
        m = list(self.methods)
        at = m.index("reeb-default") + 1 if "reeb-default" in m else len(m)
        own = (CONFIGURED,) if self.config is not None else ()
        return (*m[:at], *held_out, *m[at:], *own)

    def ranker_of(self, key: str) -> str | None:
        """The learned ranking of the REEB row ``key`` (a name or a weights file), or None
        (a baseline, or a row that ranks by REEB's own score)."""
        from ..config import get_preset

        if key == CONFIGURED:
            spec = getattr(self.config, "ranker", "none")
        elif METHODS[key].preset is None:
            return None
        else:
            spec = get_preset(METHODS[key].preset or "default").ranker
        return None if spec == "none" else spec

    @property
    def data_text(self) -> str:
        """The data folders as the tables name them."""
        return " + ".join(str(d) for d in self.data)

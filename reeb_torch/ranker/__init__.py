"""The learned ranking over REEB's candidates (``ReebConfig.ranker``; not in the paper).

REEB's windows cover the objects; its hand-weighted score V (eq. 12) cannot order them.
:class:`BoxRanker` scores each candidate from cheap per-box features and the generator
ranks by it before the final NMS. All of it lives here:

==================  ===========================================================================
module              what it holds
==================  ===========================================================================
:mod:`.features`    the per-box features (tensor ops, and one compiled pass on the CPU)
:mod:`.orientation` the edge-orientation columns (each bin's share of the gradient energy)
:mod:`.prefilter`   the compiled prefilter: the first layer of the cheap-column MLP
:mod:`.model`       :class:`BoxRanker`: the prefilter, the ranking MLPs, the class head
:mod:`.weights`     safetensors weights files and their metadata (:func:`load_ranker`)
:mod:`.step`        :class:`LearnedRanking`: the step the generator calls (prefilter, features,
                    model, class hints, refinement)
:mod:`.refine`      :class:`BoxRefiner`: the box refiner's features, model and the merge of its
                    boxes with the originals
==================  ===========================================================================

Weights are safetensors files (:func:`load_ranker`, :func:`save_ranker`); ``kitti`` ships
with the package, and ``reeb fit`` fits new ones on a user's labelled frames
(:mod:`reeb_torch.ranker.frames`).

>>> from reeb_torch.ranker import load_ranker
>>> model = load_ranker("kitti")              # a BoxRanker, eval mode
>>> logits = model(features)                  # float [K, F] -> float32 [K]
>>> logits = model.rank(features)             # the same for inference, faster on large K
"""

from .features import FEATURE_GROUPS, dropped_columns
from .model import BoxRanker
from .orientation import ORIENTATION_NAMES
from .refine import TARGET_SCALE, BoxRefiner, offset_targets, refine_feature_names, refine_features
from .step import NOT_SEEN_BY_RANKER, CandidateFeatures, LearnedRanking, keep_candidates
from .weights import (SAME_IMAGE_BITS, SHIPPED, RankerWeightsError, fitted_frames, frame_hash, hash_distance,
                      load_ranker, resolve_ranker, save_ranker, seen_hashes, shipped_path)

__all__ = ["BoxRanker", "CandidateFeatures", "LearnedRanking", "NOT_SEEN_BY_RANKER", "SHIPPED", "RankerWeightsError",
           "load_ranker", "resolve_ranker", "save_ranker", "shipped_path", "frame_hash", "hash_distance", "seen_hashes",
           "fitted_frames", "SAME_IMAGE_BITS", "BoxRefiner", "refine_features", "refine_feature_names",
           "offset_targets", "TARGET_SCALE", "FEATURE_GROUPS", "dropped_columns",
           "ORIENTATION_NAMES", "keep_candidates"]

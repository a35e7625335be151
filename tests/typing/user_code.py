"""Code as a user writes it against the public API (the README's examples), checked by mypy
(``tests/test_typing.py``): the annotations users' type checkers read (``py.typed``) must
accept it and give these types. Never run; only type-checked."""

from __future__ import annotations

from typing import assert_type

import torch
from torch import Tensor

import reeb_torch
from reeb_torch import ProposalGenerator, ReebConfig, get_preset, propose, read_image
from reeb_torch.ranker import BoxRanker, load_ranker

gen = ProposalGenerator()
img = read_image("examples/data/kitti_000001.png")
assert_type(img, Tensor)
out = gen([img])
assert_type(out, list[dict[str, Tensor]])
boxes, scores = out[0]["boxes"], out[0]["scores"]
classes = gen.classes
hints = [classes[int(i)] for i in out[0]["labels"]] if classes is not None else []
assert_type(hints, list[str])
batch = gen(torch.zeros(2, 3, 375, 1242))
assert_type(batch, list[dict[str, Tensor]])

free = ProposalGenerator(get_preset("training-free"))
mine = ProposalGenerator(ranker="mine.safetensors")
paper = ProposalGenerator(ReebConfig.paper())
small = ProposalGenerator(top_k=300, use_regions=False)
cam = ProposalGenerator(ReebConfig().with_kitti_calib("examples/data/kitti_000001_calib.txt", 1242, 375))
quota = ReebConfig(class_quota={"Pedestrian": 0.2, "Cyclist": 0.05})
shares = ReebConfig(class_quota=(0.0, 0.2, 0.05, 0.0))
assert_type(quota.replace(top_k=500), ReebConfig)
assert_type(propose([img], quota), list[dict[str, Tensor]])
assert_type(reeb_torch.warmup(quiet=True), float)
ins = gen.inspect(img)
cands = gen.candidates(img)
model = load_ranker("kitti")
assert_type(model, BoxRanker)
assert_type(model.rank(cands.features), Tensor)

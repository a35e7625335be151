"""Mistakes a user's type checker must catch through the public annotations
(``tests/test_typing.py`` expects an error on every line marked ``# error``).
Never run; only type-checked."""

from __future__ import annotations

from reeb_torch import ProposalGenerator, ReebConfig, read_image
from reeb_torch.ranker import load_ranker

gen = ProposalGenerator()
out = gen([read_image("a.png")])
boxes: int = out[0]["boxes"]  # error
ReebConfig(top_k="many")  # error
ReebConfig(class_quota={"Pedestrian": "a lot"})  # error
read_image(3)  # error
load_ranker("kitti").rank("features")  # error

"""The README's torchvision example, as a script: run it from the repository root,
``python examples/torchvision_rpn.py``; it prints what came out (the heads are untrained,
so the detections are not meaningful: the point is the plumbing)."""

import torch, torchvision
from reeb_torch import read_image
from reeb_torch.detection import ReebRPN

model = torchvision.models.detection.fasterrcnn_mobilenet_v3_large_fpn(
    weights=None, weights_backbone=None, num_classes=4)   # any GeneralizedRCNN
model = ReebRPN().attach(model).eval()                    # REEB proposals in place of its RPN
img = read_image("examples/data/kitti_000001.png").float() / 255
with torch.no_grad():
    det = model([img])[0]                                 # boxes, labels, scores

print({name: tuple(v.shape) for name, v in det.items()}, "from", type(model.rpn).__name__, "proposals")

"""The README's detector example, as a script: run it from the repository root,
``python examples/detect.py`` (the 'detect' extra); it prints what came out."""

from reeb_torch import read_image
from reeb_torch.detection import ReebDetector

det = ReebDetector.load("kitti")                      # the shipped detector: Car, Pedestrian, Cyclist
img = read_image("examples/data/kitti_000008.png")    # uint8 (3, H, W), RGB
out = det([img])[0]                                   # boxes float32 [D, 4] xyxy, labels int64 [D], scores [D]
keep = out["scores"] > 0.5
names = [det.categories[i] for i in out["labels"][keep]]  # categories[0] is the background

print(f"{int(keep.sum())} detections above 0.5: " + ", ".join(
    f"{n} {s:.2f}" for n, s in zip(names, out["scores"][keep].tolist())))

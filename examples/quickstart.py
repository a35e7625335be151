"""The README's Python quick start, as a script: run it from the repository root,
``python examples/quickstart.py``; it prints what came out."""

import torch
from reeb_torch import ProposalGenerator, get_preset, read_image

gen = ProposalGenerator()                             # the default: REEB + learned ranking, 2000 boxes
img = read_image("examples/data/kitti_000001.png")    # uint8 (3, H, W), RGB
out = gen([img])                                      # a list of images, or a (B, 3, H, W) tensor
boxes, scores = out[0]["boxes"], out[0]["scores"]     # float32 [N, 4] (x1, y1, x2, y2), [N]
hints = [gen.classes[i] for i in out[0]["labels"]]    # a class hint per box: "Car", "Pedestrian", ...

free = ProposalGenerator(get_preset("training-free"), top_k=300)  # REEB alone, 300 boxes
cam = ProposalGenerator(get_preset("training-free").with_kitti_calib(
    "examples/data/kitti_000001_calib.txt", 1242, 375))  # windows from a calibrated camera
ins = gen.inspect(img)                                # edges, road mask, regions, entropy, shares
if torch.cuda.is_available():
    out = gen.to("cuda")([img.cuda()])                # the same code on a GPU

print(f"{len(boxes)} proposals, the best {[round(v) for v in boxes[0].tolist()]} ({hints[0]}, score "
      f"{scores[0]:.2f}); training-free: {len(free([img])[0]['boxes'])}; {len(ins.regions)} regions")

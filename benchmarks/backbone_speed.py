"""The detector's frozen EfficientNet-Lite0 alone: milliseconds and map error of each way to run it.

Variants, each on the same KITTI frames resized as the detector resizes them (shorter side
``--min-size``; the rows above ``--crop-top`` cut where asked):

- ``pyramid``: :meth:`EfficientNetLite0.pyramid` as the network is defined (BatchNorm after
  every convolution, TensorFlow's padding added before each, float32, contiguous);
- ``pyramid-bf16-autocast``: the same under ``torch.autocast("cpu", torch.bfloat16)``;
- ``folded-float32`` / ``folded-bfloat16``: :class:`~reeb_torch.detection.lite0.FrozenLite0`
  (BatchNorm folded, padding inside the convolutions, ReLU6 in place, channels-last);
- ``int8-<engine>`` (``--int8``): post-training quantization of the folded float32 network
  with torch's FX graph mode (``torch.ao.quantization``, the engine's default
  configuration), calibrated on ``--calibrate`` other frames.

Map error: ``||maps − reference|| / ||reference||`` per pyramid level against ``pyramid`` in
float32, on the timed frames. Every variant runs once per pass, in turn; the median pass.

    python benchmarks/backbone_speed.py ../shared/data/kitti/images --limit 6 --int8 \\
        --out docs/results/detector/backbone

Writes ``OUT/backbone.txt`` and ``OUT/backbone.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import environment, rerun_line  # noqa: E402
from detect_speed import image_paths  # noqa: E402


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("images", nargs="+", type=Path, help="image files or folders")
    p.add_argument("--limit", type=int, default=6, help="frames timed (default 6)")
    p.add_argument("--calibrate", type=int, default=16, help="other frames that calibrate int8 (default 16)")
    p.add_argument("--min-size", type=int, nargs="+", default=[576], help="input shorter sides (default 576)")
    p.add_argument("--crop-top", type=float, default=0.0, help="share of the height cut from the top")
    p.add_argument("--int8", action="store_true", help="also int8 (torch.ao FX quantization, x86 and onednn)")
    p.add_argument("--repeats", type=int, default=3, help="timed passes")
    p.add_argument("--out", type=Path, help="folder for backbone.txt and backbone.json")
    return p.parse_args(argv)


def batches(paths: list[Path], min_size: int, crop_top: float) -> list[Any]:
    """Each frame as the detector's transform gives it (resized, normalised, padded to 32),
    the rows above ``crop_top`` cut."""
    from reeb_torch.detection import DetectorSettings, ReebDetector
    from reeb_torch.detection.feature_cache import top_rows
    from reeb_torch.io import read_image

    transform = ReebDetector(settings=DetectorSettings(min_size=min_size)).model.transform.eval()
    out = []
    for p in paths:
        batch, _ = transform([read_image(p).float() / 255.0])
        out.append(batch.tensors[:, :, top_rows(crop_top, batch.image_sizes[0][0]):].contiguous())
    return out


def traceable(folded: Any) -> Any:
    """:class:`FrozenLite0` (float32) as plain ``nn.Conv2d``/``ReLU6`` modules that FX can trace:
    inputs padded to a multiple of 32, so every stride-2 layer sees even sizes and pads
    ``k // 2 - 1`` before and ``k // 2`` after."""
    import torch
    from torch import nn

    def conv(c: Any) -> nn.Module:
        k, s = c.kernel, c.stride
        m = nn.Conv2d(c.weight.shape[1] * c.groups, c.weight.shape[0], k, s, k // 2 if s == 1 else 0,
                      groups=c.groups)
        m.weight.data, m.bias.data = c.weight.float().clone(), c.bias.float().clone()
        layers = ([nn.ZeroPad2d((k // 2 - 1, k // 2, k // 2 - 1, k // 2))] if s > 1 else []) + [m]
        return nn.Sequential(*layers, *([nn.ReLU6()] if c.relu6 else []))

    class Block(nn.Module):
        def __init__(self, b: Any) -> None:
            super().__init__()
            self.body = nn.Sequential(*[conv(c) for c in (b.expand, b.depthwise, b.project) if c is not None])
            self.residual = b.residual
            self.add = torch.ao.nn.quantized.FloatFunctional()

        def forward(self, x: Any) -> Any:
            y = self.body(x)
            return self.add.add(y, x) if self.residual else y

    class Net(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.stem = conv(folded.stem)
            self.blocks = nn.ModuleList(Block(b) for b in folded.blocks)

        def forward(self, x: Any) -> dict[str, Any]:
            x = self.stem(x)
            out = {}
            for i, b in enumerate(self.blocks):
                x = b(x)
                if i in (4, 10, 15):
                    out[{4: "0", 10: "1", 15: "2"}[i]] = x
            return out

    return Net().eval()


def int8_model(folded: Any, engine: str, calibration: list[Any]) -> Callable[[Any], Any]:
    import torch
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

    torch.backends.quantized.engine = engine
    net = traceable(folded)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prepared = prepare_fx(net, get_default_qconfig_mapping(engine), example_inputs=(calibration[0],))
        with torch.no_grad():
            for x in calibration:
                prepared(x)
        quantized = convert_fx(prepared)

    def run(x: Any) -> Any:
        torch.backends.quantized.engine = engine
        with torch.no_grad():
            return quantized(x)
    return run


def variants(args: argparse.Namespace, calibration: list[Any]) -> dict[str, Callable[[Any], Any]]:
    import torch

    from reeb_torch.detection.lite0 import FrozenLite0, load_lite0

    net = load_lite0()
    f32, bf16 = FrozenLite0(net, "float32"), FrozenLite0(net, "bfloat16")

    def autocast(x: Any) -> Any:
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            return net.pyramid(x)

    out: dict[str, Callable[[Any], Any]] = {"pyramid": lambda x: net.pyramid(x), "pyramid-bf16-autocast": autocast,
                                            "folded-float32": f32, "folded-bfloat16": bf16}
    if args.int8:
        for engine in ("x86", "onednn"):
            out[f"int8-{engine}"] = int8_model(f32, engine, calibration)
    return out


def main(argv: list[str] | None = None) -> int:
    import torch

    args = parse_args(argv)
    paths = image_paths(args.images, None)
    timed_paths, calib_paths = paths[:args.limit], paths[args.limit:args.limit + args.calibrate]
    rows = []
    for size in args.min_size:
        frames = batches(timed_paths, size, args.crop_top)
        models = variants(args, batches(calib_paths, size, args.crop_top) if args.int8 else [])
        with torch.no_grad():
            ref = [models["pyramid"](x) for x in frames]
            errors = {}
            for name, run in models.items():
                outs = [run(x) for x in frames]
                errors[name] = {k: round(statistics.mean(float((o[k].float() - r[k]).norm() / r[k].norm())
                                                         for o, r in zip(outs, ref)), 4) for k in ref[0]}
            passes: dict[str, list[float]] = {n: [] for n in models}
            for _ in range(args.repeats):
                for name, run in models.items():
                    t0 = time.perf_counter()
                    for x in frames:
                        run(x)
                    passes[name].append(1000 * (time.perf_counter() - t0) / len(frames))
        for name in models:
            rows.append({"min_size": size, "input": list(frames[0].shape[-2:]), "variant": name,
                         "ms": round(sorted(passes[name])[(len(passes[name]) - 1) // 2], 1),
                         "passes_ms": [round(v, 1) for v in passes[name]], "map_error": errors[name]})
    command = rerun_line("benchmarks/backbone_speed.py", sys.argv[1:] if argv is None else argv)
    env = environment()
    lines = [f"# rerun: {command}", f"# machine: {json.dumps(env, sort_keys=True)}",
             f"# {len(timed_paths)} frames, {args.repeats} passes, median pass; ms per frame; map error: relative "
             "L2 distance to the float32 pyramid, per level",
             f"{'input':<12}{'variant':<24}{'ms':>8}  map error (levels 0 / 1 / 2)"]
    for r in rows:
        err = " / ".join(f"{v:.4f}" for v in r["map_error"].values())
        lines.append(f"{'x'.join(map(str, r['input'])):<12}{r['variant']:<24}{r['ms']:>8.1f}  {err}")
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "backbone.txt").write_text(text + "\n")
        (args.out / "backbone.json").write_text(json.dumps({"command": command, "rows": rows, "environment": env},
                                                           indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

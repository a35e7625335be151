"""The ``reeb`` command line: every command, and where each one's work lives.

::

    reeb propose                         # the bundled KITTI sample: top-10 table + reeb_proposals.png
    reeb propose images/ --out p.jsonl   # a folder (or files, or globs) to JSON Lines / Parquet
    reeb propose images/ --out p.jsonl --resume   # after an interruption: only what is missing
    reeb show                            # the bundled sample, explained: reeb_show.png
    reeb show frame.png --label frame.txt --top 30 --out frame_reeb.png
    reeb eval data/kitti --limit 20               # the paper's Table 3 (reeb_torch.eval.command)
    reeb calibrate my_frames/ -o camera.json      # the horizon from labelled boxes, the images, or --calib
    reeb tune my_frames/ --config camera.json -o tuned.json --trials 50 --storage sqlite:///tune.db
    reeb fit my_frames/ --config camera.json -o mine.safetensors   # the learned ranking, cross-validated
    reeb detector fit my_frames/ -o det.safetensors                # a detector on REEB's proposals
    reeb detect images/ --detector det.safetensors -o dets.jsonl --kitti-dir results/

Exit codes: 0 success; 1 some images failed (each is named, in the summary and in the
output with its status) or the command failed; 2 usage error (bad option or setting, no
images found, output not writable, or being written by another run — all checked before
any work); 130 interrupted (what was done is saved; ``--resume`` continues).

Each command checks its options, builds its settings once (:func:`.common.build_config`,
from the options :func:`.common.settings_options` declares) and hands on:

=====================  ==========================================================
command                where its work lives
=====================  ==========================================================
``propose``            :mod:`.propose_local` (on the run engine, :mod:`.engine`),
                       ``--engine ray``: :mod:`.propose_ray`
``detect``             :mod:`.detect_run` (on the run engine, :mod:`.engine`)
``detector fit/show``  :mod:`.detect` (around :mod:`reeb_torch.detection`)
``show``               here, with :func:`.viz.inspection_figure`
``warmup``             here, with :func:`reeb_torch.generator.warmup`
``eval``               :mod:`reeb_torch.eval.command`
``export``             :mod:`.export`
``calibrate``          :mod:`.calibrate`
``tune``               :mod:`.tune` (around :mod:`reeb_torch.tuning`)
``fit``                :mod:`.fit` (around :mod:`reeb_torch.ranker.frames`)
=====================  ==========================================================

What they share (errors, the finite-float type, settings, device) is :mod:`.common`.
"""

from __future__ import annotations

from . import ctrl_c

_BEFORE = ctrl_c.exit_at_once()  # while this module's imports load (~0.5 s): see the end of the file

import os  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import click  # noqa: E402

from .common import (  # noqa: E402
    CONTEXT,
    Failure,
    FiniteFloat,
    device_option,
    engine_options,
    UsageProblem,
    box_table,
    build_config,
    bundled_sample,
    config_options,
    label_for,
    read_labels,
    resolve_device,
    settings_options,
)

# -- the command group -------------------------------------------------------------------

class _Reeb(click.Group):
    """The ``reeb`` group: a Ctrl-C at any time (:mod:`.ctrl_c`) exits 130 with one line and
    no traceback, as an interrupted run does, instead of click's "Aborted!" and exit 1 or
    Python's traceback; once the command has finished, with its exit code (when the process
    is the command's: ``main()`` reads ``sys.argv``)."""

    program = False  # this process runs the command line it was started with

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        before = ctrl_c.exit_at_once()  # options parsed, nothing done yet
        type(self).program = args is None and standalone_mode
        try:
            return super().main(args, prog_name, complete_var, standalone_mode, **extra)
        except SystemExit as e:
            if self.program:  # --help, --version and usage errors too
                ctrl_c.exits_with(ctrl_c.exit_code(e))
            raise
        finally:
            if not self.program:  # called from Python (a test, a script): as it was
                ctrl_c.restore(before)

    def invoke(self, ctx: click.Context):
        ctrl_c.interrupts()  # the runs catch KeyboardInterrupt to save what is done
        ended: BaseException | None = None
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            ended = click.exceptions.Exit(130)
            raise ended from None
        except BaseException as e:
            ended = e
            raise
        finally:
            if self.program:
                ctrl_c.exits_with(ctrl_c.exit_code(ended))
            else:
                ctrl_c.exit_at_once()  # the rest of main(); it puts back the caller's handler


@click.group(cls=_Reeb, context_settings=CONTEXT)
@click.version_option(package_name="reeb-torch", prog_name="reeb")
def main() -> None:
    """REEB: training-free object proposals for driving images.

    Run `reeb propose` or `reeb show` with no arguments to see the bundled KITTI sample.
    """


# -- reeb propose ------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("paths", nargs=-1, type=click.Path(readable=False))
@click.option("-o", "--out", type=click.Path(),
              help="Write one row per image here: .jsonl (JSON Lines) or .parquet.")
@click.option("--resume", is_flag=True,
              help="Keep the rows already in --out and process only the images missing there "
                   "(or that failed).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file.")
@config_options
@click.option("-b", "--batch-size", type=click.IntRange(min=1), default=4, show_default=True,
              help="Images of equal size computed together.")
@click.option("-j", "--workers", type=click.IntRange(min=0), default=None,
              help="Decoding processes running alongside the algorithm (0 = decode inline). "
                   "[default: min(2, CPUs)]")
@click.option("--viz", "viz_dir", type=click.Path(),
              help="Write a PNG per image with its top proposals into this folder.")
@click.option("--viz-top", type=click.IntRange(min=1), default=10, show_default=True,
              help="Proposals drawn per picture.")
@click.option("-r", "--recursive", is_flag=True, help="Look for images in sub-folders too.")
@click.option("--print-top", type=click.IntRange(min=0), default=None,
              help="Print a table of the top N boxes per image [default: 10 without --out, "
                   "else 0].")
@click.option("--summary-json", type=click.Path(dir_okay=False),
              help="Also write the closing summary as JSON (for scripts and benchmarks).")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar, no per-file messages.")
@engine_options("local: this process; ray: Ray Data actors (a folder of Parquet files; "
                "pip install 'reeb-torch[ray]').", "--engine ray: actors, each holding one proposal generator.")
def propose(paths, out, resume, overwrite, preset, config_file, sets, top_k, device,
            batch_size, workers, viz_dir, viz_top, recursive, print_top, summary_json, quiet,
            engine, address, actors, cpus_per_actor):
    """Object proposals for images, folders or glob patterns (PATHS).

    With no PATHS, runs on the bundled KITTI sample: prints its top proposals and writes
    reeb_proposals.png (or into --viz). A file that cannot be processed never stops the
    run: it gets an "error: ..." status, is named in the summary, and the exit code is 1.
    The output is written atomically; after Ctrl-C what is done is saved, and --resume
    continues.

    Output rows, in input order: format_version, image (as given), resolved (the
    absolute file, symlinks resolved), width, height, boxes ([x1, y1, x2, y2] in pixels,
    best first), scores, status ("ok" or "error: <file>: <reason>"), config (settings
    fingerprint). A run locks its output: a second run on it fails at once (exit 2).
    --resume matches rows on the resolved file, and also takes the finished rows a killed
    run left in a hidden .NAME.*.tmp file.
    """
    cfg, dev = build_config(preset, config_file, sets, top_k), resolve_device(device)
    if engine == "ray":
        from .propose_ray import propose_ray

        return propose_ray(paths, cfg, dev, out=out, resume=resume, overwrite=overwrite, batch_size=batch_size,
                           recursive=recursive, summary_json=summary_json, quiet=quiet, address=address,
                           actors=actors, cpus_per_actor=cpus_per_actor, viz_dir=viz_dir)
    from .propose_local import propose_local

    return propose_local(paths, cfg, dev, out=out, resume=resume, overwrite=overwrite, batch_size=batch_size,
                         workers=workers, viz_dir=viz_dir, viz_top=viz_top, recursive=recursive, print_top=print_top,
                         summary_json=summary_json, quiet=quiet)


# -- reeb warmup -------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.option("-p", "--preset", default="default", show_default=True,
              help="The preset whose kernels to compile (and those of its ranking by V).")
def warmup(preset):
    """Compile the CPU kernels once for this install (or load them from the cache), so that
    the first `reeb propose` or ProposalGenerator call does not pay for it; e.g. right after
    pip install. The cache is private to the user ($REEB_TORCH_CACHE_DIR, else
    ~/.cache/reeb-torch/numba; `off`: none), survives a reinstall of the same version, and
    replaces a damaged entry by compiling it again.
    """
    from ..config import get_preset
    from ..generator import warmup as _warmup
    from ..stages._kernel_cache import cache_dir, cache_note

    try:
        cfg = get_preset(preset)
    except (KeyError, ValueError) as e:
        raise UsageProblem(str(e))
    seconds = _warmup(cfg, cfg.unranked())
    where = cache_dir()
    click.echo(f"kernels ready in {seconds:.1f} s"
               + (f" (cached in {where})" if where else f" (not cached: {cache_note()})"), err=True)


# -- reeb show ---------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("image", required=False, type=click.Path())
@click.option("-l", "--label", type=click.Path(exists=True, dir_okay=False),
              help="KITTI label_2 file to draw as ground truth [default: <stem>.txt beside the "
                   "image, or in ../labels or ../label_2, if there].")
@click.option("--no-label", is_flag=True, help="Do not look for a label file.")
@click.option("-n", "--top", type=click.IntRange(min=1), default=20, show_default=True,
              help="Proposals drawn.")
@click.option("-o", "--out", type=click.Path(), default="reeb_show.png",
              show_default=True, help="The PNG to write.")
@config_options
def show(image, label, no_label, top, out, preset, config_file, sets, top_k, device):
    """One picture that explains REEB on IMAGE (default: the bundled KITTI sample).

    Three panels: the edge map and road mask; the region strips with their entropy H and
    their share of the proposal budget; the top proposals, coloured by rank, with the
    ground-truth boxes (and each one's best IoU over all proposals).
    """
    from .rows import file_error, hint_names
    from ..io import read_image

    cfg = build_config(preset, config_file, sets, top_k)
    dev = resolve_device(device)
    path = Path(image) if image else bundled_sample()
    if Path(out).suffix.lower() != ".png":
        raise UsageProblem(f"{out}: the picture is a PNG; give a file name ending in .png")
    out_p = Path(out)
    parent = out_p.parent if str(out_p.parent) else Path(".")
    if out_p.is_dir() or not parent.is_dir() or not os.access(parent, os.W_OK) or (
            out_p.exists() and not os.access(out_p, os.W_OK)):
        raise UsageProblem(f"{out}: cannot write there (is the folder there and writable?)")
    if not path.exists():
        raise UsageProblem(f"{path}: no such file")
    if path.is_dir():
        raise UsageProblem(f"{path}: is a folder; reeb show explains one image (reeb propose takes "
                           "folders)")
    label_path = None if no_label else (Path(label) if label else label_for(path))
    gt = read_labels(label_path) if label_path else []

    from ..generator import ProposalGenerator
    from ..io import ImageReadError
    from .viz import inspection_figure, save_figure

    try:
        img = read_image(path)
    except ImageReadError as e:
        raise Failure(str(e))
    gen = ProposalGenerator(cfg).to(dev).eval()
    t0 = time.perf_counter()
    try:
        insp = gen.inspect(img.to(dev))
    except (ValueError, TypeError) as e:
        raise Failure(file_error(path, e))
    dt = time.perf_counter() - t0
    h, w = img.shape[-2:]
    title = (f"REEB on {path.name} ({w}×{h} px): {len(insp.boxes)} proposals in {1000 * dt:.0f} ms "
             f"on {dev} — preset {preset}, config {cfg.fingerprint()}")
    fig = inspection_figure(img, insp, gt=gt, top=top, title=title, config=cfg)
    try:
        save_figure(fig, out_p)
    except OSError as e:
        raise Failure(f"{out}: cannot write ({e.strerror or e})")

    hints = hint_names(gen.classes, insp.labels)
    click.echo(box_table(str(path), (w, h), insp.boxes.cpu(), insp.scores.cpu(), min(top, 10),
                         len(insp.boxes), hints))
    ent = ", ".join(f"R{i + 1} H={float(hv):.2f} {100 * float(s):.0f}%"
                    for i, (hv, s) in enumerate(zip(insp.entropy.tolist(), insp.share.tolist())))
    click.echo(f"regions: {ent}")
    click.echo(f"road: {100 * float(insp.road_mask.float().mean()):.0f} % of pixels; "
               f"{insp.num_windows} windows scored")
    if gt:
        from .viz import _best_match

        boxes = insp.boxes.cpu().numpy()
        click.echo(f"ground truth ({label_path}):")
        for o in gt:
            iou, rank = _best_match(o.box, boxes)
            where = f"best IoU {iou:.2f} (proposal #{rank})" if iou > 0 else "no proposal overlaps it"
            click.echo(f"  {o.type:<14} {where}")
    click.echo(f"wrote {out_p.resolve()}")


# -- reeb eval ---------------------------------------------------------------------------

from ..eval.command import TABLE3_HELP, TABLE3_SHORT_HELP, run_command, table3_parameters  # noqa: E402 - imports click only


@main.command("eval", context_settings=CONTEXT, short_help=TABLE3_SHORT_HELP, help=TABLE3_HELP)
@table3_parameters()
@settings_options(run=False)  # reeb eval takes the settings reeb propose takes
@device_option
def eval_(preset, config_file, sets, device, **given):
    """``--preset / --config / --set``: given any, a row with those settings (built as
    ``reeb propose`` builds them); ``--device``: where the REEB rows run."""
    ctx = click.get_current_context()
    own = any(ctx.get_parameter_source(n) == click.core.ParameterSource.COMMANDLINE
              for n in ("preset", "config_file", "sets"))
    cfg = build_config(preset, config_file, sets, None) if own else None
    if cfg is not None and cfg.ranker != "none":  # a ranker that cannot be read: one line, before any row
        from ..ranker import RankerWeightsError, load_ranker

        try:
            load_ranker(cfg.ranker)
        except RankerWeightsError as e:
            raise UsageProblem(" ".join(str(e).split())) from None
    return run_command(config=cfg, preset=preset, device=str(resolve_device(device)), quick=True, **given)


# -- reeb export -------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("results", type=click.Path(exists=True))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False),
              help="The file to write (detectron2: a .pkl pickle).")
@click.option("--format", "fmt", type=click.Choice(["detectron2"]), default="detectron2",
              show_default=True, help="Target framework's precomputed-proposals format.")
@click.option("--ids", "ids_file", type=click.Path(exists=True, dir_okay=False),
              help="Image → id mapping (JSON object, or CSV/TSV 'image,id'); keys may be the "
                   "path as written, the file name or the stem. [default: file stems]")
@click.option("--id-type", type=click.Choice(["str", "int"]), default="str", show_default=True,
              help="int: ids such as 000123 become 123 (datasets with numeric image_id).")
@click.option("--overwrite", is_flag=True, help="Replace OUT where it exists.")
def export(results, out, fmt, ids_file, id_type, overwrite):
    """Convert RESULTS of `reeb propose` (a .jsonl/.parquet file, or the Parquet folder of
    --engine ray) into a detector framework's proposal file.

    detectron2: a pickle with ids, boxes (N×4 float32, XYXY_ABS, best first),
    objectness_logits (the scores) and bbox_mode, for MODEL.LOAD_PROPOSALS with
    DATASETS.PROPOSAL_FILES_TRAIN/TEST. Failed images are left out and named.
    """
    from . import export as E
    from .claim import claim_files  # imports torch: after the options are read

    claim_files([out], overwrite, inputs={results: "RESULTS"}, example="proposals.pkl")
    try:
        id_map = E.read_id_map(ids_file) if ids_file else None
        rows = E.read_rows(results)
        proposals, failed = E.detectron2_proposals(rows, id_map, id_type)
    except E.ExportError as e:
        raise UsageProblem(str(e))
    if not proposals["ids"]:
        raise Failure(f"{results}: no image with status ok; nothing to export")
    try:
        saved = E.write_detectron2(proposals, out)
    except E.ExportError as e:
        raise Failure(str(e))
    n = sum(len(b) for b in proposals["boxes"])
    for m in failed:
        click.echo(f"warning: left out (failed): {m}", err=True)
    click.echo(f"wrote {saved}: {len(proposals['ids'])} images, {n} proposals ({fmt}, XYXY_ABS)"
               + (f"; {len(failed)} failed images left out" if failed else ""), err=True)


# -- reeb calibrate ----------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("dirs", nargs=-1, type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), default="camera.json", show_default=True,
              help="Config file to write (reeb propose --config reads it); the labelled route's picture goes beside "
                   "it (.png).")
@click.option("--no-labels", is_flag=True,
              help="Estimate the horizon from the images even where DIRS have labels (to compare the routes).")
@click.option("--calib", type=click.Path(exists=True, dir_okay=False),
              help="A KITTI calibration file: the horizon of a level camera, P2's cy / image height (the height from "
                   "the images in DIRS, or --height).")
@click.option("--cy", type=FiniteFloat(min=0, min_open=True), metavar="PIXELS",
              help="The principal point's row: the horizon of a level camera, cy / --height.")
@click.option("--height", type=click.IntRange(min=1), metavar="PIXELS", help="The image height, for --calib or --cy.")
@click.option("--camera-height", type=FiniteFloat(min=0, min_open=True), metavar="METRES",
              help="The camera's height above the road where it is not fitted (images, intrinsics) [default: 1.65].")
@click.option("--class-height", "class_height", multiple=True, metavar="CLASS=METRES",
              help="Real height of a label class (repeatable); default KITTI's means: Car 1.53, Van 2.21, "
                   "Truck 3.25, Pedestrian 1.76, Cyclist 1.74, Tram 3.53.")
@click.option("--samples", type=click.IntRange(min=1), default=500, show_default=True,
              help="Frame-bootstrap samples for the intervals.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the bootstrap.")
@click.option("--box-factor", type=FiniteFloat(min=0, min_open=True), default=None,
              help="2D box height / 3D object height at the bottom's depth [default: 1.055, fitted on KITTI "
                   "frames, docs/results.md; 1 = the plain model].")
@click.option("--overwrite", is_flag=True, help="Replace OUT (and its picture) where they exist.")
def calibrate(dirs, out, no_labels, calib, cy, height, camera_height, class_height, samples, seed, box_factor,
              overwrite):
    """The camera's horizon row (and height) for reeb propose --config, by one of three routes:

    \b
    labels      DIRS are KITTI-format folders with labels (images/ + labels/, or image_2/ +
                label_2/): bottom - horizon = box height x camera height / class height, a
                line fitted robustly (Tukey's biweight); the horizon and the camera height,
                with frame-bootstrap intervals, the residuals per class and a picture.
    images      DIRS hold frames without labels (or --no-labels): the horizon from where
                the road's lines meet in each frame (the mode over frames, with a frame-
                bootstrap interval); the camera height stays 1.65 m or --camera-height.
    intrinsics  --calib FILE or --cy PIXELS: the horizon of a level camera, cy / image
                height (--height, or the height of the images in DIRS).

    Prints the route, the horizon and how sure it is; writes the config (horizon,
    camera_height_m) with the route's record.
    """
    from . import calibrate as C
    from ..horizon import HorizonError

    intrinsics = calib is not None or cy is not None
    if calib is not None and cy is not None:
        raise UsageProblem("give --calib FILE or --cy PIXELS, not both")
    if not intrinsics and height is not None:
        raise UsageProblem("--height goes with --calib or --cy (the images route reads each frame's own height)")
    if cy is not None and height is None:
        raise UsageProblem("--cy needs --height PIXELS (the image height it is a row of)")
    if not dirs and not intrinsics:
        raise UsageProblem("give folders of the camera's frames (DIRS), or --calib FILE, or --cy PIXELS --height PIXELS")
    labels = not intrinsics and not no_labels and all(C.has_labels(d) for d in dirs)
    if camera_height is not None and labels:
        raise UsageProblem("--camera-height: the labelled route fits the camera height from the boxes; give it "
                           "with --no-labels, --calib or --cy")
    heights = C.class_heights(class_height)
    C.check_out(Path(os.path.expanduser(out)), picture=labels, overwrite=overwrite)
    notes: list[str] = []
    picture = None
    try:
        if intrinsics:
            text, path = C.calibrate_intrinsics(out, calib, cy, height, dirs, camera_height)
        elif labels:
            text, path, picture = C.calibrate(dirs, out, heights, samples=samples, seed=seed,
                                              box_height_factor=box_factor)
        else:
            text, path, notes = C.calibrate_images(dirs, out, camera_height, samples=samples, seed=seed)
    except (HorizonError, ValueError, FileNotFoundError) as e:
        C.print_notes(getattr(e, "notes", ()))
        raise UsageProblem(" ".join(str(e).split()))
    except OSError as e:  # the writes are atomic: what was there stays
        raise Failure(f"{e.filename or out}: cannot write ({e.strerror or e}); the file that was there is "
                      "unchanged") from None
    C.print_notes(notes)
    click.echo(text)
    tail = f" and {picture}" if picture else (" (no picture: matplotlib is not installed)" if labels else "")
    click.echo(f"wrote {path}{tail}", err=True)


# -- reeb tune ---------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), default="tuned.json", show_default=True,
              help="Tuned config file (reeb propose --config reads it) with the estimate; plots beside it.")
@click.option("--trials", type=click.IntRange(min=1), default=50, show_default=True, help="Trials per study.")
@click.option("--folds", type=click.IntRange(min=2), default=3, show_default=True,
              help="Contiguous blocks of frames for the nested cross-validation.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the samplers and bootstraps.")
@click.option("--storage", help="Optuna storage URL, e.g. sqlite:///tune.db (default: in memory).")
@click.option("--resume", is_flag=True, help="Continue the studies in --storage (after Ctrl-C or a crash).")
@click.option("--timeout", type=FiniteFloat(min=0, min_open=True), help="Seconds for all the searching.")
@click.option("--balanced", is_flag=True, help="Objective: mean of the per-class recalls (default: micro).")
@click.option("--space", "space_file", type=click.Path(exists=True, dir_okay=False),
              help="JSON search space {field: {type: float|int|categorical, low, high | choices}}.")
@click.option("-k", "--proposals", "k", type=click.IntRange(min=1), default=2000, show_default=True,
              help="Proposals counted per frame.")
@click.option("--iou", type=FiniteFloat(0, 1, min_open=True), default=0.7, show_default=True,
              help="IoU an object needs.")
@click.option("--limit", type=click.IntRange(min=1), help="Use only the first N frames of each folder.")
@click.option("--score", "score_file", type=click.Path(exists=True, dir_okay=False),
              help="No search: score this config file (e.g. a tuned.json) against the base on DIRS.")
@settings_options("The base settings: the comparison, and what the search changes.", run=False)
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
@click.option("--overwrite", is_flag=True, help="Replace OUT and its plots where they exist.")
def tune(dirs, out, trials, folds, seed, storage, resume, timeout, balanced, space_file, k, iou, limit,
         score_file, preset, config_file, sets, quiet, overwrite):
    """Search the settings that matter on labelled KITTI-format folders (DIRS) with Optuna,
    and estimate by nested cross-validation over frames how they do on new frames, beside the
    base config on the same frames. Runs on the CPU; needs the extra 'tune'.
    """
    from . import tune as R

    base = build_config(preset, config_file, sets, None)
    try:
        if score_file:
            click.echo(R.run_score(dirs, build_config(preset, score_file, (), None), base, k, iou, balanced, limit))
            return
        R.check_out(Path(os.path.expanduser(out)), overwrite)
        record = R.run_tune(dirs, out, base, space_file, trials, folds, seed, storage, resume, timeout, balanced,
                            k, iou, limit, quiet)
    except KeyboardInterrupt:
        where = f"the finished trials are in {storage}; rerun with --resume" if storage else \
            "nothing was kept (no --storage)"
        click.echo(f"interrupted: {where}", err=True)
        sys.exit(130)
    except (ValueError, FileNotFoundError, ImportError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    click.echo(record["text"])


# -- reeb fit ----------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("dirs", nargs=-1, required=True, type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", type=click.Path(dir_okay=False), default="ranker.safetensors", show_default=True,
              help="Weights file to write; a config for reeb propose --config is written beside it (.json).")
@click.option("--folds", type=click.IntRange(min=2), default=5, show_default=True,
              help="Blocks of frames for the cross-validated estimate.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the negatives' sample and the fit.")
@click.option("--whole-drives", is_flag=True,
              help="Leave every frame of a held-out block's drives out of its training frames (ids naming a drive, "
                   "as KITTI tracking's t0000_000012), not only those within 2 frames: an estimate for drives "
                   "the model never saw.")
@click.option("--epochs", type=click.IntRange(min=1),
              help="Passes over the rows [default: 15; with --init, 10].")
@click.option("--hidden", help="Hidden layer widths, comma-separated [default: 64,64].")
@click.option("--init", "init", metavar="MODEL",
              help="Fine-tune MODEL (a shipped name such as kitti, or a weights file) on DIRS instead of "
                   "fitting from scratch: for a few labelled frames of another camera (its widths are its own).")
@click.option("--balance", type=FiniteFloat(0, 2), default=0.5, show_default=True,
              help="Weigh each class's objects by (objects / the class's objects)^BALANCE (1: classes equal).")
@click.option("--mirror", is_flag=True,
              help="Fit also on each training frame's mirror image (flipped left to right, its boxes with it); "
                   "the held-out frames of the estimate stay as they are.")
@click.option("--jitter", type=FiniteFloat(0, 1), default=0.0, show_default=True,
              help="Fit also on a copy of each training frame with its contrast scaled by 1 ± up to JITTER and "
                   "up to JITTER × 255 grey levels added (drawn per frame, seeded); 0: none.")
@click.option("--hard-negatives", "hard", type=FiniteFloat(0, 1), default=0.0, show_default=True,
              help="Draw the ranking MLP's negatives at this fraction from the candidates the prefilter keeps "
                   "(where the MLP ranks at run time) in place of the uniform sample; 0: off "
                   "(docs/results.md, \"Tight boxes and a wider cut\").")
@click.option("--no-orientation", "no_orientation", is_flag=True,
              help="Fit a model without the edge-orientation columns (faster to run, ranked less well on KITTI).")
@click.option("--drop-features", "drop", metavar="NAMES",
              help="Feature columns the model does not read, comma-separated: column names or the group 'place' "
                   "(where the box lies in the frame: top, bottom, centre_x, off_centre, at_border).")
@click.option("--refiner", is_flag=True,
              help="Also fit a box refiner into the weights (side offsets of the best boxes, applied with "
                   "--set refine_top=N; off by default: docs/results.md, \"Box refinement\").")
@click.option("--val", multiple=True, type=click.Path(exists=True, file_okay=False), metavar="DIR",
              help="Labelled folder kept out of the fit and scored instead of the cross-validation (one fit, one "
                   "pass over it: for data sets where --folds fits would take long; repeatable).")
@click.option("-k", "--proposals", "k", type=click.IntRange(min=1), default=2000, show_default=True,
              help="Proposals counted per frame.")
@click.option("--iou", type=FiniteFloat(0, 1, min_open=True), default=0.7, show_default=True,
              help="IoU an object needs.")
@click.option("--limit", type=click.IntRange(min=1), help="Use only the first N frames of each folder.")
@settings_options("The settings the ranking is fitted for.", run=False)
@engine_options("Where each frame's candidates and rows are made: this process, or Ray Data actors (training "
                "runs here, from the rows; pip install 'reeb-torch[ray]').",
                "--engine ray: actors, each making frames' rows.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
@click.option("--overwrite", is_flag=True, help="Replace OUT and the config beside it where they exist.")
def fit(dirs, out, folds, seed, whole_drives, epochs, hidden, init, balance, mirror, jitter, hard, no_orientation,
        drop, refiner, val, k, iou, limit, preset, config_file, sets, engine, address, actors, cpus_per_actor, quiet,
        overwrite):
    """Fit the learned ranking on labelled KITTI-format folders (DIRS) for another camera, and
    estimate by cross-validation over blocks of frames how it does on frames it never saw,
    beside the training-free settings and the shipped model on the same frames. Writes the
    weights (OUT, safetensors) and a config that reeb propose --config takes. Runs on the CPU.

    With a few labelled frames (a dozen or so), fine-tune the shipped model (--init kitti)
    rather than fit one from scratch.

    The frames are read one at a time and their rows kept on disk beside OUT until the
    weights are written: memory does not grow with the frames, and a fit that was stopped,
    started again with the same command, goes on from where it was.
    """
    import dataclasses
    import os

    from ..ranker.fit import FitOptions
    from . import fit as R

    shared = {os.path.realpath(v) for v in val} & {os.path.realpath(d) for d in dirs}
    if shared:
        raise click.BadParameter(f"{', '.join(sorted(shared))} is also a training folder: --val scores frames the "
                                 "fit does not see", param_hint="--val")

    cfg = build_config(preset, config_file, sets, None)
    if init and hidden:
        raise click.BadParameter("a fine-tuned model keeps its own widths: give --hidden or --init, not both",
                                 param_hint="--hidden")
    try:
        widths = tuple(int(w) for w in (hidden or "64,64").split(","))
    except ValueError:
        raise click.BadParameter(f"{hidden!r}: expected widths such as 64,64", param_hint="--hidden") from None
    opts = FitOptions(hidden=widths, seed=seed, balance=balance, init=init, mirror=mirror, jitter=jitter,
                      hard_negatives=hard, refine_hidden=(64, 64) if refiner else None, orientation=not no_orientation,
                      drop_features=tuple(x.strip() for x in (drop or "").split(",") if x.strip()))
    if epochs is not None:
        opts = dataclasses.replace(opts, **{"tune_epochs" if init else "epochs": epochs})
    command = " ".join(["reeb fit", *map(shlex.quote, sys.argv[2:])])
    try:
        engine_ray = (address, actors, cpus_per_actor) if engine == "ray" else None
        record = R.run_fit(dirs, out, cfg, opts, folds, k, iou, limit, quiet, command, whole_drives, val, engine_ray,
                           overwrite=overwrite)
    except (ValueError, FileNotFoundError) as e:
        raise UsageProblem(" ".join(str(e).split()))
    click.echo(record["text"])


# -- reeb detector fit / show, reeb detect ------------------------------------------------

from .detector import detector as _detector  # noqa: E402 - a click group: imports click only

main.add_command(_detector)


@main.command(context_settings=CONTEXT)
@click.argument("paths", nargs=-1, required=True, type=click.Path(readable=False))
@click.option("--detector", "detector_path", default="kitti", show_default=True, type=click.Path(dir_okay=False),
              help="The detector file reeb detector fit wrote, or a shipped name: kitti (Car, Pedestrian, "
                   "Cyclist; fitted on KITTI frames: reeb detector show kitti).")
@click.option("-o", "--out", type=click.Path(dir_okay=False),
              help="Write one row per image here: .jsonl (JSON Lines) or .parquet.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out file (and the files in --kitti-dir).")
@click.option("--resume", is_flag=True,
              help="Keep the rows this detector already wrote to --out; detect only on the images missing there "
                   "(or that failed).")
@click.option("--kitti-dir", type=click.Path(file_okay=False),
              help="Write one KITTI result file per image here (<image stem>.txt), as KITTI's devkit scores them; "
                   "an empty folder, or one of this output's results with --resume.")
@click.option("--viz", "viz_dir", type=click.Path(file_okay=False),
              help="Save a picture per image here, with each detection's class and score.")
@click.option("--min-score", type=FiniteFloat(0, 1), default=0.0, show_default=True,
              help="Keep detections scoring at least this (in every output).")
@click.option("--viz-min-score", type=FiniteFloat(0, 1), default=0.3, show_default=True,
              help="Draw detections scoring at least this in the --viz pictures.")
@click.option("-b", "--batch-size", type=click.IntRange(min=1), default=8, show_default=True,
              help="Images run through the detector together (REEB's proposals as one batch; on a CPU the "
                   "backbone still takes them one by one).")
@click.option("-j", "--workers", type=click.IntRange(min=0), default=None,
              help="Decoding processes beside the detector (0 = decode inline). [default: min(2, CPUs)]")
@device_option
@click.option("-r", "--recursive", is_flag=True, help="Look for images in sub-folders too.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar, no per-file messages.")
def detect(paths, detector_path, out, overwrite, resume, kitti_dir, viz_dir, min_score, viz_min_score, batch_size,
           workers, device, recursive, quiet):
    """Run a trained detector on images (PATHS: files, folders or globs) and write its
    detections: rows to OUT, KITTI result files to --kitti-dir, pictures to --viz.

    A file that cannot be processed never stops the run: it gets an "error: ..." row, is
    named in the summary, and the exit code is 1. The output is written atomically; after
    Ctrl-C what is done is saved, and --resume continues (also from the rows a killed run
    left in a hidden .NAME.*.tmp file).
    """
    from .detect_run import load_detector, run_detect

    if not (out or kitti_dir or viz_dir):
        raise UsageProblem("nothing to write: give -o/--out, --kitti-dir or --viz")
    det, det_id, dev = load_detector(detector_path, device)
    return run_detect(paths, det, det_id, dev, out=out, overwrite=overwrite, resume=resume, kitti_dir=kitti_dir,
                      viz_dir=viz_dir, min_score=min_score, viz_min_score=viz_min_score, batch_size=batch_size,
                      workers=workers, recursive=recursive, quiet=quiet)

ctrl_c.restore(_BEFORE)  # the command's imports are done; main() takes over

if __name__ == "__main__":
    main()

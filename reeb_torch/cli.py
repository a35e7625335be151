"""The ``reeb`` command line: ``propose``, ``show``, ``eval`` and ``export``.

::

    reeb propose                         # the bundled KITTI sample: top-10 table + reeb_proposals.png
    reeb propose images/ --out p.jsonl   # a folder (or files, or globs) to JSON Lines / Parquet
    reeb propose images/ --out p.jsonl --resume   # after an interruption: only what is missing
    reeb show                            # the bundled sample, explained: reeb_show.png
    reeb show frame.png --label frame.txt --top 30 --out frame_reeb.png
    reeb eval ../shared/data/kitti --limit 20     # the paper's Table 3 (reeb_torch.eval.table3)

Exit codes: 0 success; 1 some images failed (each is named, in the summary and in the
output with its status) or the command failed; 2 usage error (bad option or setting, no
images found, output not writable, or being written by another run — all checked before
any work); 130 interrupted (what was done is saved; ``--resume`` continues).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import click

CONTEXT = dict(help_option_names=["-h", "--help"], max_content_width=100)
SAMPLE_NAME = "kitti_000001.png"


class UsageProblem(click.ClickException):
    """A one-line error with exit code 2 (bad input given on the command line)."""

    exit_code = 2


class Failure(click.ClickException):
    """A one-line error with exit code 1 (the command could not do its work)."""

    exit_code = 1


# -- shared helpers ----------------------------------------------------------------------

def repo_root() -> Path:
    """The source checkout the package is installed from (editable install)."""
    # this file's package folder, not reeb_torch.__file__: that is None when the package is
    # imported as a namespace package (an editable install made before __init__.py existed)
    return Path(__file__).resolve().parent.parent


def bundled_sample() -> Path:
    """The sample KITTI frame that ``reeb propose`` / ``reeb show`` use without arguments."""
    p = repo_root() / "examples" / "data" / SAMPLE_NAME
    if not p.is_file():
        raise UsageProblem(
            f"the bundled sample image is missing (expected {p}; it ships with the source "
            "checkout, not with an installed wheel); give an image path instead")
    return p


def _parse_value(text: str, choices: tuple[str, ...] = ()) -> Any:
    """A ``--set`` value: one of the field's ``choices`` (the words of a ``Literal`` field,
    kept as written even where they read as JSON, such as ``none``), else JSON, else
    ``none``/``null`` as None, ``true``/``false``, or the bare string."""
    word = text.strip()
    if word in choices:
        return word
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        low = word.lower()
        if low in ("none", "null"):
            return None
        if low in ("true", "false"):
            return low == "true"
        return text


#: The words ``--set`` takes for a bool field of ReebConfig (case-insensitive).
BOOL_WORDS = {"true": True, "yes": True, "on": True, "1": True,
              "false": False, "no": False, "off": False, "0": False}


def _parse_bool(field: str, text: str) -> bool:
    """``--set FIELD=WORD`` for a bool field: one of :data:`BOOL_WORDS`, else a usage error."""
    word = text.strip()
    if len(word) >= 2 and word[0] == word[-1] and word[0] in "\"'":
        word = word[1:-1].strip()  # --set 'use_regions="false"'
    try:
        return BOOL_WORDS[word.lower()]
    except KeyError:
        raise click.BadParameter(
            f"{field}={text!r}: {field} is a yes/no setting; use true/false, yes/no, on/off "
            "or 1/0", param_hint="--set") from None


def _field_kinds() -> tuple[set[str], dict[str, tuple[str, ...]]]:
    """Names of the ReebConfig fields whose type is ``bool``, and the words of each field
    whose type is a ``Literal`` of strings (from the dataclass)."""
    import dataclasses
    import typing

    from .config import ReebConfig

    hints = typing.get_type_hints(ReebConfig)
    bools: set[str] = set()
    words: dict[str, tuple[str, ...]] = {}
    for f in dataclasses.fields(ReebConfig):
        hint = hints.get(f.name)
        if hint is bool:
            bools.add(f.name)
        elif typing.get_origin(hint) is typing.Literal:
            words[f.name] = tuple(a for a in typing.get_args(hint) if isinstance(a, str))
    return bools, words


def build_config(preset: str, config_file: str | None, sets: Sequence[str], top_k: int | None):
    """The ReebConfig from a preset, then a JSON file of fields, then ``--set`` pairs, then
    ``--top-k`` (each later source overrides the earlier ones).

    A bool field given with ``--set`` takes true/false, yes/no, on/off or 1/0; a field of
    named choices takes one of its words as written (``shadow_score=none`` is the word
    ``'none'``, not None); other fields take JSON (``3``, ``1.5``, ``[1, 2]``, ``null``) or a
    bare string. Any error (a bad word, an unknown field, a value ReebConfig rejects) is a
    usage error, exit code 2.
    """
    from .config import ReebConfig, get_preset

    d = get_preset(preset).to_dict()
    if config_file:
        try:
            loaded = json.loads(Path(config_file).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError) as e:
            raise click.BadParameter(f"{config_file}: cannot read ({e})", param_hint="--config")
        except json.JSONDecodeError as e:
            raise click.BadParameter(f"{config_file}: not valid JSON ({e})", param_hint="--config")
        if isinstance(loaded, dict) and isinstance(loaded.get("config"), dict):
            loaded = loaded["config"]  # a saved record with a "config" entry
        if not isinstance(loaded, dict):
            raise click.BadParameter(f"{config_file}: expected a JSON object of ReebConfig fields",
                                     param_hint="--config")
        d.update(loaded)
    bools, words = _field_kinds() if sets else (set(), {})
    for item in sets:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise click.BadParameter(f"{item!r}: expected FIELD=VALUE, e.g. scale=1.0",
                                     param_hint="--set")
        name = key.strip()
        d[name] = _parse_bool(name, value) if name in bools else _parse_value(value, words.get(name, ()))
    if top_k is not None:
        d["top_k"] = top_k
    try:
        return ReebConfig.from_dict(d)
    except (TypeError, ValueError, ArithmeticError) as e:
        raise click.BadParameter(" ".join(str(e).split()) or type(e).__name__,
                                 param_hint="--config/--set/--top-k")


def resolve_device(name: str):
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        raise click.BadParameter(f"{name!r} is not a device (try cpu, cuda, cuda:1 or auto)",
                                 param_hint="--device")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise click.BadParameter("CUDA was asked for but is not available here (use --device cpu)",
                                 param_hint="--device")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise click.BadParameter(f"{name}: only {torch.cuda.device_count()} CUDA device(s)",
                                 param_hint="--device")
    return dev


def config_options(f):
    """``--preset``, ``--config``, ``--set``, ``--top-k``, ``--device`` (shared)."""
    from .config import PRESETS

    options = [
        click.option("--preset", type=click.Choice(sorted(PRESETS)), default="default",
                     show_default=True, help="Named settings to start from."),
        click.option("--config", "config_file", type=click.Path(exists=True, dir_okay=False),
                     help="JSON file of ReebConfig fields applied over the preset."),
        click.option("--set", "sets", multiple=True, metavar="FIELD=VALUE",
                     help="Change one ReebConfig field (repeatable), e.g. --set scale=1.0."),
        click.option("--top-k", type=click.IntRange(min=1), default=None,
                     help="Proposals kept per image (default: the config's top_k, 2000)."),
        click.option("--device", default="auto", show_default=True,
                     help="cpu, cuda, cuda:N, or auto (CUDA when available)."),
    ]
    for opt in reversed(options):
        f = opt(f)
    return f


def _label_for(image: Path) -> Path | None:
    """A KITTI label file for ``image``: beside it, or in ../labels or ../label_2."""
    for cand in (image.with_suffix(".txt"),
                 image.parent.parent / "labels" / f"{image.stem}.txt",
                 image.parent.parent / "label_2" / f"{image.stem}.txt"):
        if cand.is_file():
            return cand
    return None


def _read_labels(path: Path) -> list:
    from .data import read_kitti_labels

    try:
        objs = read_kitti_labels(path)
    except (OSError, ValueError) as e:
        raise Failure(f"{path}: cannot read the label file ({' '.join(str(e).split())})")
    return [o for o in objs if o.type != "DontCare"]


def _box_table(name: str, size: tuple[int, int], boxes, scores, n: int, total: int) -> str:
    w, h = size
    lines = [f"{name}  {w}×{h} px  {total} proposals" + (f" (top {min(n, total)})" if total else "")]
    if total:
        lines.append(f"{'rank':>5} {'x1':>8} {'y1':>8} {'x2':>8} {'y2':>8} {'score':>10}")
        for i, (b, s) in enumerate(zip(boxes[:n].tolist(), scores[:n].tolist()), 1):
            lines.append(f"{i:>5} {b[0]:8.1f} {b[1]:8.1f} {b[2]:8.1f} {b[3]:8.1f} {s:10.4f}")
    return "\n".join(lines)


def _ms(seconds: float, n: int) -> str:
    return f"{1000 * seconds / n:.1f} ms/img" if n else "n/a"


# -- the command group -------------------------------------------------------------------

@click.group(context_settings=CONTEXT)
@click.version_option(package_name="reeb-torch", prog_name="reeb")
def main() -> None:
    """REEB: training-free object proposals for driving images.

    Run `reeb propose` or `reeb show` with no arguments to see the bundled KITTI sample.
    """


# -- reeb propose ------------------------------------------------------------------------

@main.command(context_settings=CONTEXT)
@click.argument("paths", nargs=-1, type=click.Path())
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
@click.option("--engine", type=click.Choice(["local", "ray"]), default="local", show_default=True,
              help="local: this process; ray: Ray Data actors (a folder of Parquet files; "
                   "pip install 'reeb-torch[ray]').")
@click.option("--address", default=None,
              help="--engine ray: the Ray cluster (auto, ray://HOST:PORT) [default: a local Ray "
                   "instance sized to this machine].")
@click.option("--actors", type=click.IntRange(min=1), default=1, show_default=True,
              help="--engine ray: actors, each holding one proposal generator.")
@click.option("--cpus-per-actor", type=click.FloatRange(min=0, min_open=True), default=None,
              help="--engine ray: CPUs each actor reserves (and its torch threads) "
                   "[default: leaves one CPU to Ray's read/write tasks].")
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
    if engine == "ray":
        from .distributed import cli_propose

        return cli_propose(paths, out=out, resume=resume, overwrite=overwrite, preset=preset,
                           config_file=config_file, sets=sets, top_k=top_k, device=device,
                           batch_size=batch_size, recursive=recursive, summary_json=summary_json,
                           quiet=quiet, address=address, actors=actors,
                           cpus_per_actor=cpus_per_actor, viz_dir=viz_dir)
    from . import batch as B

    cfg = build_config(preset, config_file, sets, top_k)
    dev = resolve_device(device)
    fingerprint = cfg.fingerprint()
    workers = B.default_workers() if workers is None else workers
    echo_err = (lambda m: None) if quiet else (lambda m: click.echo(m, err=True))

    # 1. inputs ---------------------------------------------------------------------------
    sample_mode = not paths
    try:
        images, notes = B.find_images([bundled_sample()] if sample_mode else paths, recursive)
    except B.NoImagesError as e:
        raise UsageProblem(str(e))
    for n in notes:
        echo_err(f"note: {n}")

    # 2. outputs, checked before any work ------------------------------------------------------
    if resume and not out:
        raise UsageProblem("--resume needs --out (the file to continue)")
    # rows are written in input order: ``slots`` maps an input position to its row (kept
    # from before, or computed), ``first_rows`` are kept rows of images not among the inputs
    plan = _ResumePlan(images)
    stale: list[Path] = []
    if out:
        try:
            B.check_output(out)
            # one writer per output: a second run fails here, before any work (exit 2)
            lock = B.lock_output(out)
        except B.OutputError as e:
            raise UsageProblem(str(e))
        click.get_current_context().call_on_close(lock.release)
        exists = Path(out).exists()
        if exists and not (resume or overwrite):
            raise UsageProblem(f"{out} exists; add --resume to continue it or --overwrite to "
                               "replace it")
        stale = B.stale_temp_files(out)  # left by killed runs (we hold the lock: none is live)
        stale_rows: list[dict] = []
        if stale and not overwrite:
            for t in stale:
                got, problems = B.read_partial_results(t, B.output_format(out))
                stale_rows += got
                for p in problems:
                    echo_err(f"warning: {p}")
            if stale_rows and not resume:
                raise UsageProblem(
                    f"{', '.join(t.name for t in stale)} beside {out} hold{'s' if len(stale) == 1 else ''} "
                    f"{len(stale_rows)} finished rows of a run that was killed; add --resume to use "
                    "them, or --overwrite to discard them")
        if overwrite or not stale_rows:
            for t in stale:  # nothing in them to keep
                t.unlink(missing_ok=True)
            stale = []
        if resume and (exists or stale_rows):
            rows: list[dict] = []
            if exists:
                try:
                    rows, problems = B.read_results(out)
                except B.OutputError as e:
                    raise UsageProblem(str(e))
                for p in problems:
                    echo_err(f"warning: {p}")
            other = {r.get("config") for r in rows + stale_rows
                     if r.get("status") == "ok"} - {fingerprint}
            if other:
                raise UsageProblem(
                    f"{out} was made with different settings (config {', '.join(sorted(map(str, other)))}, "
                    f"now {fingerprint}); use the same options, another --out, or --overwrite")
            before = len(images)
            plan.keep(rows + stale_rows)
            images = plan.todo_paths()
            echo_err(f"resume: {plan.kept} images already in {out}"
                     + (f" ({len(stale_rows)} rows recovered from a killed run)" if stale_rows else "")
                     + (f", {plan.duplicates} duplicate rows dropped" if plan.duplicates else "")
                     + f", {before - len(images)} of them among the inputs; {len(images)} to do")
            if not images and not stale and not plan.duplicates:
                click.echo(f"Nothing to do: all {before} images are already in {out}.", err=True)
                return
    viz_path = Path(viz_dir) if viz_dir else None
    if viz_path is not None:
        try:
            viz_path.mkdir(parents=True, exist_ok=True)
            B.check_output(viz_path / "probe.jsonl")
        except (OSError, B.OutputError) as e:
            raise UsageProblem(f"--viz {viz_path}: cannot write pictures there "
                               f"({getattr(e, 'strerror', None) or e})")
    sample_png = Path("reeb_proposals.png") if sample_mode and viz_path is None else None
    if sample_png is not None and not os.access(sample_png.parent.resolve(), os.W_OK):
        raise UsageProblem(f"cannot write {sample_png.resolve()}: the current folder is not "
                           "writable (use --viz DIR)")
    if print_top is None:
        print_top = 0 if out else 10
    if not out and not sample_mode and viz_path is None:
        echo_err("note: no --out given: proposals are printed, not saved")
    viz_names = _viz_names(images) if viz_path is not None else {}

    # 3. the run --------------------------------------------------------------------------
    import torch

    from .generator import ProposalGenerator
    from .viz import draw_proposals, save_png

    try:
        gen = ProposalGenerator(cfg).to(dev).eval()
    except (TypeError, ValueError, ArithmeticError) as e:
        raise UsageProblem(f"the settings are not usable: {' '.join(str(e).split())}")
    try:
        writer = B.open_writer(out) if out else None
    except B.OutputError as e:
        raise UsageProblem(str(e))
    if writer is not None:
        # an unexpected error or exit must not leave the temporary file behind
        click.get_current_context().call_on_close(writer.discard)
        writer.write(plan.first_rows)
    cs = B.CriticalSection()  # a row is written whole, and counted, or not at all
    saved_now = [0]  # rows of this run in the writer

    def emit(todo_pos: int, row: dict | None) -> None:
        """Place this run's row for input ``todo_pos`` and write what is next in input order."""
        plan.put(todo_pos, row)
        if writer is not None:
            rows = plan.ready()
            writer.write(r for r, _ in rows)
            saved_now[0] += sum(new for _, new in rows)
    gt = _read_labels(_label_for(images[0])) if sample_mode and _label_for(images[0]) else None

    stats = dict(images=len(images), ok=0, failed=0, proposals=0, algo_s=0.0)
    failures: list[str] = []
    from tqdm import tqdm

    bar = tqdm(total=len(images), unit="img", disable=True if quiet else None, file=sys.stderr,
               dynamic_ncols=True, desc="reeb propose")

    def fail(item, message: str, size=None) -> None:
        with cs:
            stats["failed"] += 1
            failures.append(message)
            emit(item.index, B.error_row(item.path, message, fingerprint, size or item.size))
        if not quiet:
            bar.write(f"error: {message}", file=sys.stderr)

    def finish(item, result, algo_s: float) -> None:
        h, w = item.image.shape[-2:]
        boxes, scores = result["boxes"].cpu(), result["scores"].cpu()
        with cs:
            stats["ok"] += 1
            stats["proposals"] += len(boxes)
            emit(item.index, B.result_row(item.path, w, h, boxes, scores, fingerprint)
                 if writer is not None else None)
        if print_top:
            bar.write(_box_table(item.path, (w, h), boxes, scores, print_top, len(boxes)) + "\n",
                      file=sys.stdout)
        pictures = []
        if viz_path is not None:
            pictures.append(viz_path / viz_names[item.path])
        if sample_png is not None:
            pictures.append(sample_png)
        for pic in pictures:
            title = f"{Path(item.path).name}: top {min(viz_top, len(boxes))} of {len(boxes)} proposals"
            try:
                save_png(pic, draw_proposals(item.image, boxes, scores, top=viz_top,
                                             gt=gt if pic == sample_png else None, title=title))
            except OSError as e:
                bar.write(f"warning: {pic}: cannot write picture ({e.strerror or e})", file=sys.stderr)

    def run_batch(items: list) -> None:
        x = torch.stack([it.image for it in items]).to(dev, non_blocking=True)
        t0 = time.perf_counter()
        results = gen(x)
        results = [{k: v.cpu() for k, v in r.items()} for r in results]
        dt = time.perf_counter() - t0
        stats["algo_s"] += dt
        for it, r in zip(items, results):
            finish(it, r, dt / len(items))

    interrupted = False
    first_done = None  # (time, images done, algorithm seconds) after the first computed batch
    t_start = time.perf_counter()
    stream = B.decoded_images(images, workers=workers, min_side=cfg.min_window,
                              prefetch=batch_size, pin_memory=dev.type == "cuda")
    previous_handlers = cs.install()  # Ctrl-C, and a polite kill (SIGTERM) treated like it
    try:
        # max_lag: a group of a rare size waits at most this many inputs, which bounds the
        # rows held back to be written in input order
        for group in B.size_batches(stream, batch_size, max_lag=max(64, 4 * batch_size)):
            if not group[0].ok:
                fail(group[0], group[0].error)
            else:
                try:
                    run_batch(group)
                except (ValueError, TypeError, RuntimeError) as e0:
                    if B.caused_by_interrupt(e0):
                        raise
                    # find the culprit(s): one image at a time
                    for it in group:
                        try:
                            run_batch([it])
                        except (ValueError, TypeError, RuntimeError) as e1:
                            if B.caused_by_interrupt(e1):
                                raise
                            fail(it, B.file_error(it.path, e1))
            bar.update(len(group))
            if first_done is None and stats["ok"]:
                first_done = (time.perf_counter(), stats["ok"] + stats["failed"], stats["algo_s"])
            if stats["failed"]:
                bar.set_postfix(failed=stats["failed"], refresh=False)
    except KeyboardInterrupt:
        interrupted = True
    except Exception as e:  # a Ctrl-C that a library wrapped on its way out (B.caused_by_interrupt)
        if not B.caused_by_interrupt(e):
            raise
        interrupted = True
    finally:
        for sig in previous_handlers:  # a second Ctrl-C must not break the saving
            signal.signal(sig, signal.SIG_IGN)
        stream.close()
        bar.close()
    wall = time.perf_counter() - t_start

    # 4. save and summarise -----------------------------------------------------------------
    saved = None
    try:
        if writer is not None:
            rows = plan.rest()  # after an interrupt: the rows held back, still in input order
            writer.write(r for r, _ in rows)
            saved_now[0] += sum(new for _, new in rows)
            try:
                saved = writer.commit()
            except OSError as e:
                raise Failure(f"{out}: cannot save the results ({e.strerror or e}); the old file, "
                              "if any, is unchanged")
            for t in stale:  # their rows are in the output now
                t.unlink(missing_ok=True)
    finally:
        for sig, h in previous_handlers.items():
            signal.signal(sig, h)
    done = stats["ok"] + stats["failed"]
    summary = dict(images=len(images), processed=done, ok=stats["ok"], failed=stats["failed"],
                   proposals=stats["proposals"],
                   ms_per_image=1000 * wall / done if done else None,
                   algorithm_ms_per_image=1000 * stats["algo_s"] / stats["ok"] if stats["ok"] else None,
                   workers=workers, batch_size=batch_size, device=str(dev), config=fingerprint,
                   **_steady(first_done, t_start + wall, done, stats),
                   out=str(saved) if saved else None, rows=writer.rows_written if writer else None,
                   saved=saved_now[0] if writer else None,
                   interrupted=interrupted, failures=failures)
    lines = [_count_line(done, stats["ok"], stats["failed"], stats["proposals"])]
    if done:
        lines.append(f"time: {wall:.1f} s, {_ms(wall, done)} end to end; {_ms(stats['algo_s'], stats['ok'])} "
                     f"in the algorithm ({workers} decoding worker{'s' if workers != 1 else ''}, "
                     f"batch {batch_size}, {dev})")
    if saved:
        lines.append(f"wrote {saved} ({writer.rows_written} rows"
                     + (f", {plan.kept_written} kept from before" if plan.kept_written else "") + ")")
    if viz_path is not None and stats["ok"]:
        lines.append(f"pictures in {viz_path}/")
    if sample_png is not None and stats["ok"]:
        lines.append(f"wrote {sample_png.resolve()} (top {viz_top} proposals"
                     + (", ground truth in green" if gt else "") + ")")
    lines += _failures_and_summary(failures, summary_json, summary)
    if interrupted:
        if saved:
            left = len(images) - saved_now[0]  # counted as written: the summary matches the file
            how = f"run the same command with --resume to do the {left} left"
            if "--resume" in sys.argv:
                how = f"run the same command again to do the {left} left"
            lines.append(f"interrupted: {saved_now[0]} of {len(images)} images saved in {saved}; {how}")
        else:
            lines.append(f"interrupted after {done} of {len(images)} images; nothing was saved "
                         "(no --out)")
    click.echo("\n".join(lines), err=True)
    if interrupted:
        sys.exit(130)
    if stats["failed"]:
        sys.exit(1)


class _ResumePlan:
    """Which inputs to compute, and the output rows in input order.

    Rows are matched on the resolved file (:func:`reeb_torch.batch.resolved_path`, stored
    in each row as ``resolved``; rows of older files without it are resolved against the
    current folder), so a run from another folder, through a symlink or with an absolute
    path finds them. Per file the first ``ok`` row is kept, and other rows of it dropped;
    an ``error`` row is kept only for a file that is not among the inputs (the others are
    computed again). Kept rows of files not among the inputs come first in the output, in
    their old order; then one row per input, in input order.
    """

    def __init__(self, images: Sequence[Path]) -> None:
        from .batch import resolved_path

        self.images = list(images)
        self.keys = [resolved_path(p) for p in self.images]
        self.first_rows: list[dict] = []
        self.slots: dict[int, tuple[dict, bool]] = {}  # input position -> (row, new in this run)
        self.todo = list(range(len(self.images)))  # input positions to compute
        self.kept = self.duplicates = self.kept_written = 0
        self._next = 0

    def keep(self, rows: Sequence[dict]) -> None:
        """Take the rows of an earlier run (the output, then a killed run's temp files)."""
        from .batch import resolved_path

        def key(r: dict) -> str:
            return str(r.get("resolved") or resolved_path(str(r["image"])))

        best: dict[str, dict] = {}
        order: list[str] = []
        for r in rows:
            k = key(r)
            if k not in best:
                best[k] = r
                order.append(k)
            else:
                self.duplicates += 1
                if best[k].get("status") != "ok" and r.get("status") == "ok":
                    best[k] = r
        position = {k: i for i, k in enumerate(self.keys)}
        for k in order:
            r = best[k]
            ok = r.get("status") == "ok"
            self.kept += ok
            if k not in position:
                self.first_rows.append(r)
            elif ok:
                self.slots[position[k]] = (r, False)
        self.todo = [i for i in range(len(self.images)) if i not in self.slots]
        self.kept_written = len(self.first_rows)  # written first, before this run's rows

    def todo_paths(self) -> list[Path]:
        return [self.images[i] for i in self.todo]

    def put(self, todo_pos: int, row: dict | None) -> None:
        """This run's row for ``todo_paths()[todo_pos]`` (None: no output, only count)."""
        self.slots[self.todo[todo_pos]] = (row, True)

    def ready(self) -> list[tuple[dict, bool]]:
        """Rows that can be written now: the next ones in input order, no gap before them."""
        out = []
        while self._next in self.slots:
            out.append(self.slots.pop(self._next))
            self._next += 1
        return self._count([o for o in out if o[0] is not None])

    def rest(self) -> list[tuple[dict, bool]]:
        """All rows still held back, in input order (at the end, or after an interrupt)."""
        out = [self.slots.pop(i) for i in sorted(self.slots)]
        self._next = len(self.images)
        return self._count([o for o in out if o[0] is not None])

    def _count(self, rows: list[tuple[dict, bool]]) -> list[tuple[dict, bool]]:
        self.kept_written += sum(not new for _, new in rows)
        return rows


def _count_line(done: int, ok: int, failed: int, proposals: int) -> str:
    """The first line of a run's closing summary (local and Ray engines)."""
    return (f"{done} image{'s' if done != 1 else ''}: {ok} ok, {failed} failed; {proposals} proposals"
            + (f" ({proposals / ok:.0f} per image)" if ok else ""))


def _failures_and_summary(failures: Sequence[str], summary_json: str | None, summary: dict) -> list[str]:
    """Closing-summary lines naming the failed images; writes ``summary`` to ``summary_json``
    (a warning line instead if it cannot be written). Shared by the local and Ray engines."""
    lines = []
    if failures:
        lines.append(f"failed ({len(failures)}):")
        lines += [f"  {m}" for m in failures]
    if summary_json:
        try:
            Path(summary_json).write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
        except OSError as e:
            lines.append(f"warning: {summary_json}: cannot write the summary ({e.strerror or e})")
    return lines


def _steady(first_done, t_end: float, done: int, stats: dict) -> dict:
    """Throughput after the first computed batch (which pays the one-off warm-up)."""
    if first_done is None or done <= first_done[1]:
        return dict(steady_ms_per_image=None, steady_algorithm_ms_per_image=None)
    t1, n1, a1 = first_done
    n = done - n1
    return dict(steady_ms_per_image=1000 * (t_end - t1) / n,
                steady_algorithm_ms_per_image=1000 * (stats["algo_s"] - a1) / n)


def _viz_names(images: Sequence[Path]) -> dict[str, str]:
    """A distinct PNG file name per image: ``<stem>.png``, ``<stem>-<n>.png`` on clashes."""
    from collections import Counter

    stems = Counter(Path(p).stem for p in images)
    names: dict[str, str] = {}
    used: set[str] = set()
    for i, p in enumerate(images):
        stem = Path(p).stem
        name = f"{stem}.png" if stems[stem] == 1 else f"{stem}-{i + 1}.png"
        while name in used:
            name = f"{stem}-{i + 1}-{len(used)}.png"
        used.add(name)
        names[str(p)] = name
    return names


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
    from .batch import file_error
    from .io import read_image

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
    label_path = None if no_label else (Path(label) if label else _label_for(path))
    gt = _read_labels(label_path) if label_path else []

    from .generator import ProposalGenerator
    from .io import ImageReadError
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

    click.echo(_box_table(str(path), (w, h), insp.boxes.cpu(), insp.scores.cpu(), min(top, 10),
                          len(insp.boxes)))
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

@main.command(context_settings=dict(CONTEXT, ignore_unknown_options=True))
@click.argument("kitti_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--limit", type=click.IntRange(min=1), help="Use only the first N frames.")
@click.option("-o", "--out", type=click.Path(file_okay=False), default="runs/table3",
              show_default=True, help="Folder for the table, CSV/JSON and plots.")
@click.option("--methods", help="Comma-separated methods (see python -m reeb_torch.eval --help).")
@click.argument("extra", nargs=-1, type=click.UNPROCESSED)
def eval(kitti_dir, limit, out, methods, extra):  # noqa: A001 - the command's name
    """Recall table (the paper's Table 3) and plots on a KITTI-format folder.

    Runs reeb_torch.eval.table3 (as benchmarks/table3.py does); further options (e.g.
    --frames 0:39 40:59, --max-proposals 1000, --batch 8) are passed on to it.
    """
    from .eval import table3 as table3_module

    argv = ["--data", str(kitti_dir), "--out", str(out)]
    if limit:
        argv += ["--limit", str(limit)]
    if methods:
        argv += ["--methods", *[m.strip() for m in methods.split(",") if m.strip()]]
    argv += list(extra)
    try:
        table3_module.main(argv, prog="python -m reeb_torch.eval")
    except SystemExit as e:  # argparse errors (2), --help (0), or a message: exit 1
        if e.code is None or isinstance(e.code, int):
            sys.exit(e.code or 0)
        raise Failure(" ".join(str(e.code).split()))


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
def export(results, out, fmt, ids_file, id_type):
    """Convert RESULTS of `reeb propose` (a .jsonl/.parquet file, or the Parquet folder of
    --engine ray) into a detector framework's proposal file.

    detectron2: a pickle with ids, boxes (N×4 float32, XYXY_ABS, best first),
    objectness_logits (the scores) and bbox_mode, for MODEL.LOAD_PROPOSALS with
    DATASETS.PROPOSAL_FILES_TRAIN/TEST. Failed images are left out and named.
    """
    from . import export as E

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


if __name__ == "__main__":
    main()

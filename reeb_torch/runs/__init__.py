"""The ``reeb`` command and the runs behind it.

=====================  ==============================================================
module                 what it holds
=====================  ==============================================================
:mod:`.cli`            the ``reeb`` command: every command's options, and ``show``
                       and ``warmup``; its opening comment says where each command's
                       work lives
:mod:`.common`         what the commands share: errors and exit codes, the finite-float
                       option type, settings from the command line, the device, the
                       output's claim (checked and locked)
:mod:`.engine`         the run engine of every command that turns images into rows:
                       inputs, the steps of a run, the closing summary and exit codes
:mod:`.run_output`     the engine's output file: the lock, a killed run's rows, the
                       resume plan, the ordered writer
:mod:`.side_outputs`   the engine's folders: ``--viz`` pictures, ``--kitti-dir`` results
:mod:`.propose_local`  ``reeb propose`` on this machine (the generator on the engine)
:mod:`.propose_ray`    ``reeb propose --engine ray``
:mod:`.detect_run`     ``reeb detect`` (a trained detector on the engine)
:mod:`.detect`         ``reeb detector fit`` and ``reeb detector show``
:mod:`.calibrate`      ``reeb calibrate``
:mod:`.tune`           ``reeb tune``
:mod:`.fit`            ``reeb fit``
:mod:`.inputs`         finding the images: files, folders and glob patterns expanded
:mod:`.decoding`       decoding them in DataLoader workers, batches of equal size
:mod:`.rows`           the result rows: their schema, formatting, error rows
:mod:`.output_files`   the output file: format, writers and readers, what a killed run
                       left beside it
:mod:`.output_lock`    one writer per output: the lock beside it
:mod:`.ctrl_c`         what a Ctrl-C does while the command starts, runs and has
                       finished, and the critical section around writing a row
:mod:`.distributed`    the Ray engine, a library: ``propose_dataset``, ``write_results``
:mod:`.export`         ``reeb export``: result rows to detectron2's precomputed proposals
:mod:`.viz`            the pictures (``reeb show``, ``--viz``, crop sheets)
:mod:`.detector_fit`   ``reeb detector fit``: its inputs checked before any work, the
                       training and its held-out scores
=====================  ==============================================================

``reeb propose`` and ``reeb detect`` read top to bottom (:mod:`.engine`):
:func:`.engine.find_inputs` lists the images, :func:`.run_output.plan_output` secures the
output before any work (its lock, a killed run's rows, the rows ``--resume`` keeps),
:class:`.side_outputs.PictureFolder` and :class:`.side_outputs.KittiFolder` check their
folders, :func:`.decoding.decoded_images` decodes in worker processes while the model runs
(``reeb propose`` groups images of equal size: :func:`.decoding.size_batches`), each image
becomes one row (:func:`.rows.result_row`, or :func:`.rows.error_row` for a file that
failed) placed in input order by :class:`.run_output.OrderedWriter` inside a
:class:`.ctrl_c.CriticalSection`, and :meth:`.output_files.ResultWriter.commit` renames the
finished file into place before the closing summary.

The libraries (inputs, decoding, rows, output_files, output_lock, ctrl_c, distributed,
export, viz) do not import the commands (cli, common, engine, run_output, side_outputs,
propose_local, propose_ray, detect, detect_run, calibrate, tune, fit); the algorithm
(:mod:`reeb_torch.generator`) imports nothing from here.
"""

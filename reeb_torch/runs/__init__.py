"""The ``reeb`` command and the runs behind it.

=====================  ==============================================================
module                 what it holds
=====================  ==============================================================
:mod:`.cli`            the ``reeb`` command: ``propose``, ``show``, ``eval``, ``export``
:mod:`.common`         what the command's runs share: errors and exit codes, settings
                       from the command line, the device, the closing summary
:mod:`.propose_local`  ``reeb propose`` on this machine
:mod:`.propose_ray`    ``reeb propose --engine ray``
:mod:`.inputs`         finding the images: files, folders and glob patterns expanded
:mod:`.decoding`       decoding them in DataLoader workers, batches of equal size
:mod:`.rows`           the result rows: their schema, formatting, error rows
:mod:`.output_files`   the output file: format, writers and readers, what a killed run
                       left beside it
:mod:`.output_lock`    one writer per output: the lock beside it
:mod:`.ctrl_c`         what a Ctrl-C does while the command starts, runs and has
                       finished, and the critical section around writing a row
:mod:`.distributed`    the Ray engine, a library: ``propose_dataset``, ``write_results``
:mod:`.export`         result rows to detectron2's precomputed proposals
:mod:`.viz`            the pictures (``reeb show``, ``--viz``, crop sheets)
:mod:`.detector_fit`   ``reeb detector fit``: its inputs checked before any work, the
                       training and its held-out scores
=====================  ==============================================================

``reeb propose`` reads top to bottom: :func:`.inputs.scan_images` lists the images,
:func:`.output_files.check_output` and :func:`.output_lock.lock_output` secure the output
before any work, :func:`.decoding.decoded_images` decodes in worker processes while
:func:`.decoding.size_batches` groups images of equal size for the generator, each image
becomes one row (:func:`.rows.result_row`, or :func:`.rows.error_row` for a file that
failed) written in input order inside a :class:`.ctrl_c.CriticalSection`, and
:meth:`.output_files.ResultWriter.commit` renames the finished file into place.

The libraries (inputs, decoding, rows, output_files, output_lock, ctrl_c, distributed,
export, viz) do not import the command (cli, common, propose_local, propose_ray); the
algorithm (:mod:`reeb_torch.generator`) imports nothing from here.
"""

"""The ``reeb`` command and the runs behind it.

====================  ===============================================================
module                what it holds
====================  ===============================================================
:mod:`.cli`           the ``reeb`` command: ``propose``, ``show``, ``eval``, ``export``
:mod:`.common`        what the command's runs share: errors and exit codes, settings
                      from the command line, the device, the closing summary
:mod:`._ctrl_c`       what a Ctrl-C does while the command starts, runs and has finished
:mod:`.propose_local` ``reeb propose`` on this machine
:mod:`.propose_ray`   ``reeb propose --engine ray``
:mod:`.batch`         building blocks of a run: finding and decoding images, result rows,
                      writers and readers, the output lock
:mod:`.distributed`   the Ray engine, a library: ``propose_dataset``, ``write_results``
:mod:`.export`        result rows to detectron2's precomputed proposals
:mod:`.viz`           the pictures (``reeb show``, ``--viz``, crop sheets)
====================  ===============================================================

The libraries (batch, distributed, export, viz) do not import the command (cli, common,
propose_local, propose_ray); the algorithm (:mod:`reeb_torch.generator`) imports nothing
from here.
"""

"""Data on disk that the package reads and writes.

- :mod:`reeb_torch.datasets.kitti`: KITTI-format folders (``images/`` + ``labels/`` +
  ``calib/``, or KITTI's ``image_2/`` + ``label_2/``): the label reader and a ``torch``
  dataset of frames with their boxes and calibration.
"""

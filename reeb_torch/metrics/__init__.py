"""The measures the package reports, for proposals and for detections.

- :mod:`reeb_torch.metrics.recall`: recall of proposals at k and IoU, average recall,
  KITTI's difficulty levels, the paired sign test and bootstrap intervals;
- :mod:`reeb_torch.metrics.kitti_ap`: KITTI's 2D detection AP (|R40 and |R11), with the
  frame bootstrap and the paired bootstrap of two detectors.
"""

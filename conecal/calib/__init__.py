"""Calibration from a known phantom at free poses (``motion: free``): pose
search without a log, one bundle adjustment with shared intrinsics and
detector distortion, distortion family chosen on held-out markers."""

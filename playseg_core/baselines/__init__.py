"""Segmentation baselines of the paper, and the one place a segmentation method is chosen by name.

- unloc.py: UnLoc-style per-step classification over the instructions + background, cropping windows;
- tridet.py: TriDet-style feature pyramid with trident boundary heads, top-1 detection per window;
- random_windows.py: random windows labelled by the labelling model;
- changepoint.py: PELT changepoints (ruptures) labelled by the labelling model;
- registry.py: method name (ps, unloc, tridet, random, changepoint) -> train / segment;
- common.py: what they share (options and budget, the Segmenter interface, windows, how the window
  models train through the one loop, playseg_core/training/loop.py).

Generic: every method reads a dataset through the step encoders chosen from its features (ps/encoders.py),
so none knows any domain. docs/baselines.md maps them to the paper.
"""

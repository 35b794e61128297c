"""Gaussian splat: seeding, differentiable CPU rendering, brief optimisation, cleaning, PLY and video.

Import from the modules, e.g. ``from ffrecon.splat.stage import SplatOptions, run_splat_from_prediction``:

- :mod:`ffrecon.splat.stage`: ``run_splat_from_prediction`` (the stage), ``run_splat`` (explicit seed),
  ``SplatOptions``, ``SplatResult``, ``split_views``; its parts: :mod:`ffrecon.splat.options`,
  :mod:`ffrecon.splat.result`, :mod:`ffrecon.splat.evaluate` (render and score), :mod:`ffrecon.splat.outputs` (files)
- :mod:`ffrecon.splat.seed`: ``seed_from_prediction``, ``seed_from_reconstruction``
- :mod:`ffrecon.splat.render`: ``render`` (CPU, differentiable); :mod:`ffrecon.splat.render_gsplat` (CUDA)
- :mod:`ffrecon.splat.optimize` (its parts: :mod:`ffrecon.splat.optimize_options`, :mod:`ffrecon.splat.train_views`,
  :mod:`ffrecon.splat.trainable`), :mod:`ffrecon.splat.densify`, :mod:`ffrecon.splat.clean`
- :mod:`ffrecon.formats.splat_ply`: 3DGS ``splat.ply`` read and write; :mod:`ffrecon.splat.video`: the fly-through
"""

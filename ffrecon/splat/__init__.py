"""Gaussian splat: seeding, differentiable CPU rendering, brief optimisation, cleaning.

Import from the modules, e.g. ``from ffrecon.splat.stage import SplatOptions, run_splat``:

- :mod:`ffrecon.splat.stage`: ``run_splat`` (the stage), ``SplatOptions``, ``SplatResult``
- :mod:`ffrecon.splat.seed`: ``seed_from_prediction``, ``seed_from_reconstruction``
- :mod:`ffrecon.splat.render`: ``render`` (CPU, differentiable); :mod:`ffrecon.splat.render_gsplat` (CUDA)
- :mod:`ffrecon.splat.optimize`, :mod:`ffrecon.splat.densify`, :mod:`ffrecon.splat.clean`
"""

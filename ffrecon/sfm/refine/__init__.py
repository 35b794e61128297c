"""The refinement seeded by the model's cameras: matching guided by them, screening, dense evidence,
relocalisation, weak links and the bundle adjustment; what ends in ``sparse/0``.

Together because they are the steps of one adjustment (:func:`ffrecon.sfm.refine.run.run_refine`).
"""

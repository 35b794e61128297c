"""Pose comparison: the field's metrics between two sets of cameras, and the comparisons the report lists
(the model, COLMAP and the refinement against each other and against reference poses).

Apart because it only measures: no stage's decision but the evidence's reads it.
"""

"""COLMAP's own run on the photos (features, pairing, mapping, two-view models) and the gates on its model.

Together because they are one independent witness: nothing here reads the refinement, which reads this.
"""

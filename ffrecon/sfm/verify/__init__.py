"""The evidence on the final cameras: each camera confirmed, contradicted or unchecked, and the gates on them.

Apart because it judges both the refinement and COLMAP's model, reading each and written by neither.
"""

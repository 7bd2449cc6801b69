"""``simgen eval compare``: SNUG, its ablations, the vertex-L2 GRU, supervised models, LBS and the
simulation on a dataset's held-out sequences, as the thesis's ch. 5 tables (docs/learn.md).

    from simgen.learn import load_garment_data
    from simgen.learn.comparison import compare_models
    results = compare_models(["runs/snug", "runs/l2", "runs/tiny"], load_garment_data("data/tiny"), "runs/compare")

Modules: :mod:`.contestants` (which folder is which model, labels), :mod:`.metrics` (mean
curvature, vertices inside the body, costs), :mod:`.run` (the measurements), :mod:`.tables` (Tables
5.1-5.3 and the error tables) and :mod:`.outputs` (Markdown, JSON, plot, USD, MP4).
"""

from simgen.learn.comparison.metrics import curvature_error, mean_curvature
from simgen.learn.comparison.run import compare_models
from simgen.learn.comparison.tables import build_tables

__all__ = ["compare_models", "build_tables", "mean_curvature", "curvature_error"]

"""Learned garment models (thesis ch. 4): garment fit MLP, wrinkle GRU, baselines, evaluation.

    from simgen.learn import load_garment_data, make_split, train_fit, train_wrinkle, evaluate_garment
    data = load_garment_data("datasets/tiny/tshirt_1k")        # store + ground truth (eqs. 4.4, 4.5)
    split = make_split(data, "motion")                         # or "shape": hold out extreme shapes too
    train_fit(data, "runs/tshirt", split)                      # R_G -> runs/tshirt/fit/
    train_wrinkle(data, "runs/tshirt", split)                  # R_L -> runs/tshirt/wrinkle/
    fit_linear_baselines(data, "runs/tshirt", split)           # LR baselines
    model = load_garment_model("runs/tshirt")                  # T_c + R_G + R_L, skinned, post-processed
    pred = model.predict(betas, poses, trans, fps)             # pred.vertices (T, V, 3) [m]
    metrics = evaluate_garment("runs/tshirt", data, "runs/tshirt/eval")

SNUG (thesis ch. 5), self-supervised, no dataset:

    train_snug("tshirt", "runs/snug")                          # -> runs/snug/snug/
    model = load_snug_model("runs/snug")                       # the SNUG model (thesis ch. 5)
    pred = model.rollout(load_motion("walk_fast"), betas)      # pred.vertices (T, V, 3) [m]

The same network trained with vertex L2 on a store (thesis Fig. 5.6), and the ch. 5 comparison:

    train_gru_l2(data, "runs/l2", split)                       # -> runs/l2/snug/ (a SnugModel)
    compare_models(["runs/snug", "runs/l2", "runs/tshirt"], data, "runs/compare")   # Tables 5.1-5.3

See docs/learn.md for the choices made where the thesis is silent and where we depart from it.
"""

from simgen.learn.checkpoint import check_identity, load_model, model_size_mb, read_config, save_model
from simgen.learn.collision import DEFAULT_CLEARANCE, CollisionSurface, push_out
from simgen.learn.data import (SPLIT_MODES, GarmentData, SequenceData, Split, attach_ground_truth, load_garment_data,
                               make_split, stack_sequences)
from simgen.learn.evaluate import THESIS, evaluate_garment, format_summary, time_inference
from simgen.learn.features import FEATURE_MODES, feature_size, motion_features
from simgen.learn.garment_model import (GarmentModel, Prediction, StreamState, joint_transforms, lbs_baseline,
                                        linear_baseline, load_garment_model, load_linear_baselines, load_split)
from simgen.learn.models import GarmentFitMLP, GarmentTemplate, LinearRegressor, WrinkleGRU
from simgen.learn.skinning import inverse_lbs_torch, lbs_torch
from simgen.learn.train import (FitConfig, TrainResult, WrinkleConfig, fit_linear_baselines, save_template,
                                train_fit, train_wrinkle)
from simgen.learn.snug import (SnugConfig, SnugModel, SnugNet, SnugResult, load_snug_model, snug_tracks, train_snug,
                               window_loss)
from simgen.learn.gru_l2 import train_gru_l2
from simgen.learn.comparison import compare_models

__all__ = [
    "GarmentFitMLP", "WrinkleGRU", "LinearRegressor", "GarmentTemplate", "GarmentModel", "Prediction",
    "StreamState", "load_garment_model", "load_linear_baselines", "load_split", "lbs_baseline", "linear_baseline",
    "joint_transforms", "GarmentData", "SequenceData", "Split", "SPLIT_MODES", "load_garment_data",
    "attach_ground_truth", "make_split", "stack_sequences", "FitConfig", "WrinkleConfig", "TrainResult",
    "train_fit", "train_wrinkle", "fit_linear_baselines", "save_template", "evaluate_garment", "format_summary",
    "time_inference", "THESIS", "save_model", "load_model", "read_config", "check_identity", "model_size_mb",
    "CollisionSurface", "push_out", "DEFAULT_CLEARANCE", "FEATURE_MODES",
    "feature_size", "motion_features", "lbs_torch", "inverse_lbs_torch",
    "SnugConfig", "SnugModel", "SnugNet", "SnugResult", "train_snug", "load_snug_model", "snug_tracks", "window_loss",
    "train_gru_l2", "compare_models",
]

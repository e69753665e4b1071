"""Does the network earn its lead on the objects? Recipes trained for the hidden objects, chosen on validation.

    python -m experiments.studies.objects [--rows paper balanced ...] [--variants ours ours_s]
        [--seeds 3] [--workdir DIR] [--state DIR] [--hours H] [--report-only] [--out FILE]

Each row (:data:`ROWS`) is the ``cpu`` preset's main job (``python -m experiments.train``: the
preset's data, 400 steps, its checkpoint kept on validation, every classic method tuned on
validation, the test split and the independent set scored per frame) with a few config
overrides: the paper's recipe as the preset ran it, then the levers of issue 87 one by one
(choosing the checkpoint on the object-balanced PSNR, object-balanced losses, the object term,
a wider network, a longer schedule). Each row's run folder lives in the store
(``$NLOSJAX_HOME/runs/objects/<row>``, :mod:`experiments.store`); a finished row is not trained
again, an interrupted one resumes from its checkpoints, or on a fresh clone from the state each
row mirrors into ``state/<row>`` (committed; ``--hours H`` pauses the study after H hours).

**Choices on validation only.** After training, every row's models and the classic methods (at
the settings the row's main job tuned) are scored frame by frame on the validation split
(``<workdir>/<row>/results/val_scores.npz``). The row the preset should ship is the one whose
Ours has the highest mean validation object-balanced PSNR over its seeds, among the rows whose
main job fits the preset's budget (:data:`NOT_ELIGIBLE`; :func:`choose`); the test split and the
independent set only write the final tables.

**The report** (``results/objects.md``, objects first): per row and set, every method's object
scores (object intensity error, balanced PSNR beside the all-zero image's, recall, precision,
F1, object depth error) and the whole-image PSNR beside its all-zero floor, mean [95 % interval
over sequences and seeds]; then, for each row, each learned model minus every classic method on
each object score, paired on the same frames (:func:`nlosjax.evaluation.scores.compare_scores`),
and Ours minus Ours-S. Whether a goal of issue 87 holds is read off those intervals.
"""

from __future__ import annotations

import pathlib

#: This study's results folder.
RESULTS = pathlib.Path(__file__).resolve().parent / "results"
#: Each row's committed resumable state (``state/<row>``; ``experiments.train --resume-from``).
STATE = pathlib.Path(__file__).resolve().parent / "state"

_SELECT = ("--config.train.stop.metric=psnr_balanced",)
_BALANCED = ("--config.train.loss.balance=1.0", "--config.train.loss.object_intensity=0.0") + _SELECT
#: Row -> (what it changes, the ``experiments.train`` overrides over the ``cpu`` preset).
ROWS = {
    "paper": ("the preset's recipe: the paper's whole-image losses with the object intensity term (weight "
              "3), the checkpoint kept on the validation intensity PSNR", ()),
    "select": ("the preset's recipe, the checkpoint kept on the validation object-balanced PSNR", _SELECT),
    "balanced": ("object-balanced intensity and depth losses (object and background pixels weigh half each), "
                 "no object term, kept on the balanced PSNR", _BALANCED),
    "balanced_obj": ("object-balanced losses with the object term (weight 3), kept on the balanced PSNR",
                     _BALANCED[:1] + _SELECT),
    "blend": ("half-balanced losses (balance 0.5) with the object term (weight 3), kept on the balanced PSNR",
              ("--config.train.loss.balance=0.5",) + _SELECT),
    # 4 channels through the physics layer and a refinement of width 8 ran 5-12 s a step on 2 cores
    # (the preset's: about 0.5 s), past any main job's budget: the wider network widens the features alone.
    "wide": ("object-balanced losses, twice the feature channels (width 16)",
             _BALANCED + ("--config.model.width=16",)),
    "long": ("object-balanced losses, three times the schedule (1200 steps)",
             _BALANCED + ("--config.train.steps=1200",)),
}
#: Rows the preset cannot take as its default: the main job (``experiments.train``) must stay within
#: its 20-minute budget on 2 cores, and three times the schedule does not.
NOT_ELIGIBLE = ("long",)
#: Object scores of the report and of the goals: metric -> whether higher is better.
OBJECT_SCORES = ("intensity_mae_object", "psnr_balanced", "recall", "precision", "f1", "rmse_object")
#: The sets every row is scored on: label -> the main job's per-frame scores file.
#: The pseudo-row of the weights shipped now (``nlosjax/weights/cpu-*``), scored on validation only.
SHIPPED = "shipped"
SETS = {"validation": "val_scores.npz", "test": "scores.npz", "independent": "table1_independent_scores.npz"}

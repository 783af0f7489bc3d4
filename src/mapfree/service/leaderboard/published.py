"""Published results (the papers' tables), beside the leaderboards but never ranked with submissions: they were
measured on the real Map-free dataset, which this server's ground truth need not be. Only numbers the papers
state are filled in; the rest stay empty."""

from __future__ import annotations

PAPER = "Arnold et al., ECCV 2022 / later published results"
MAPFREE_TEST = "Map-free test (real)"
MAPFREE_VAL = "Map-free val (real)"

REFERENCE_ROWS: list[dict] = [
    {
        "name": "MASt3R + DUNE encoder",
        "dataset": MAPFREE_TEST,
        "metrics": {"vcre_auc": 0.95},
        "note": "current best known",
    },
    {
        "name": "MASt3R (own metric depth)",
        "dataset": MAPFREE_TEST,
        "metrics": {"vcre_auc": 0.93, "med_trans": 0.36, "med_rot": 2.2},
        "note": "~300 ms/pair",
    },
    {"name": "DUSt3R", "dataset": MAPFREE_TEST, "metrics": {"vcre_auc": 0.70}, "note": ""},
    {"name": "LoFTR + KBR depth", "dataset": MAPFREE_TEST, "metrics": {"vcre_auc": 0.63}, "note": "best before MASt3R"},
    {
        "name": "MicKey (released model)",
        "dataset": MAPFREE_VAL,
        "metrics": {"vcre_auc": 0.72, "vcre_prec": 0.45, "med_trans": 1.90, "med_rot": 37.1},
        "note": "",
    },
    {
        "name": "RPR R(q)+t",
        "dataset": MAPFREE_VAL,
        "metrics": {"vcre_auc": 0.29, "med_trans": 2.37, "med_rot": 32.4, "med_vcre": 169.0},
        "note": "paper baseline",
    },
]

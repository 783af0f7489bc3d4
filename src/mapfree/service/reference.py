"""The paper's published rows (SPEC §5), shown on the leaderboards as reference entries (not submissions).
Only numbers the paper states are filled in; the rest stay empty."""

from __future__ import annotations

PAPER = "Arnold et al., ECCV 2022 / later published results"

REFERENCE_ROWS: dict[str, list[dict]] = {
    "test": [
        {"name": "MASt3R + DUNE encoder", "metrics": {"vcre_auc": 0.95}, "note": "current best known"},
        {"name": "MASt3R (own metric depth)", "metrics": {"vcre_auc": 0.93, "med_trans": 0.36, "med_rot": 2.2},
         "note": "medians; ~300 ms/pair"},
        {"name": "DUSt3R", "metrics": {"vcre_auc": 0.70}, "note": ""},
        {"name": "LoFTR + KBR depth", "metrics": {"vcre_auc": 0.63}, "note": "best before MASt3R"},
    ],
    "val": [
        {"name": "MicKey (released model)", "metrics": {"vcre_auc": 0.72, "med_trans": 1.90, "med_rot": 37.1},
         "note": "precision 0.45"},
        {"name": "RPR R(q)+t", "metrics": {"vcre_auc": 0.29, "med_trans": 2.37, "med_rot": 32.4, "med_vcre": 169.0},
         "note": "paper baseline"},
    ],
}

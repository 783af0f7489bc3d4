"""MASt3R and DUSt3R (Naver Labs, ECCV 2024 / CVPR 2024), ported: the asymmetric two-view network, its
checkpoint reader, the 512 preprocessing and the fast reciprocal matcher. Weights are the user's download.

Modules: ``config`` (constructor arguments, parsed not evaluated), ``rope``/``blocks``/``dpt``/``heads``/
``model`` (the network), ``published`` (the checkpoints' names and addresses, no torch), ``checkpoint``
(``.pth`` and hub folders, strict), ``preprocess``, ``reciprocal``, ``engine`` (one forward per pair, shared by
the matcher and the depth source). Fill-rule stand-in weights for tests: ``mapfree_dev.standins.mast3r``
(in a checkout, not in the wheel).
"""

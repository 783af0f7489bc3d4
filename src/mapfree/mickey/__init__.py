"""MicKey (Barroso-Laguna et al., CVPR 2024: *Matching 2D Images in 3D*), ported: metric keypoints from a frozen
DINOv2, their matching by a dual softmax, and the probabilistic Procrustes solver. Weights are the user's download.

Modules: ``config`` (the shipped YAML, read not trusted), ``dinov2`` (the ViT/14 backbone, its size read from
the weight file), ``heads`` (the four keypoint heads), ``model`` (network and matching matrix), ``preprocess``
(540x720 input, intrinsics scaled), ``published`` (the files' names and addresses, no torch), ``checkpoint``
(the files, in ``mickey/`` of a weights folder by the one weights rule; loaded strictly), ``engine`` (one
network shared by the matcher and the depth source). Fill-rule stand-in weights for tests:
``mapfree_dev.standins.mickey`` (in a checkout, not in the wheel).
The solver is ``mapfree.solvers.mickey``.
"""

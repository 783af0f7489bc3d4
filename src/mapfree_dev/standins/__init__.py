"""Stand-in weights: the published networks' layouts filled by a deterministic rule (each tensor from a seed of
its own name), so that tests and benchmarks run every path without the published files. ``mast3r``: MASt3R /
DUSt3R (``fill_value``, the rule itself); ``mickey``: MicKey's checkpoint and DINOv2 backbone."""

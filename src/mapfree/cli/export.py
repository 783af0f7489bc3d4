"""``mapfree export --matcher NAME -o model.onnx``: a network of the MASt3R family as ONNX graphs for onnxruntime."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import HelpFormatter

DESCRIPTION = """\
Write the network of a MASt3R-family matcher (mast3r, dust3r, dune-mast3r, dune-mast3r-small) as two ONNX graphs (opset 17, float32, dynamic
batch): OUTPUT holds the encoder and OUTPUT's NAME.decoder.onnx beside it the decoders and heads, so that a
reference photo is encoded once and paired with every query. The input size is fixed: the network input of
photos of --photo-size at --size (the matcher's long_side). A graph whose weights pass 2 GiB keeps them in
FILE.data beside it (ONNX external data); --external-data forces it. Both files are checked by onnx.checker.

Run them with the matcher's option backend=onnxruntime (mapfree match --backend onnxruntime --onnx OUTPUT; a
method's matcher_opts; or KIND.onnx in the weights folder). The weights are the published checkpoint found by the
weights rule (`mapfree weights mast3r`), or --weights.
"""

EPILOG = """\
examples:
  mapfree export --matcher mast3r -o mast3r.onnx
  mapfree export --matcher dust3r -o ~/.cache/mapfree/weights/dust3r.onnx --size 512 --photo-size 720x540
  mapfree match a.jpg b.jpg --matcher mast3r --backend onnxruntime --onnx mast3r.onnx
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "export",
        help="a MASt3R-family network as ONNX graphs for onnxruntime",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--matcher", required=True, help="mast3r, dust3r, dune-mast3r (ViT-B encoder) or dune-mast3r-small (ViT-S)"
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="the encoder graph to write (NAME.onnx)")
    p.add_argument(
        "--size", type=int, help="network input long side, pixels (default: the published size, 512; DUNE-MASt3R 518)"
    )
    p.add_argument(
        "--photo-size",
        default="540x720",
        metavar="WxH",
        help="width x height of the photos the graphs will take (any photo of that aspect; default: 540x720, "
        "Map-free's)",
    )
    p.add_argument("--weights", help="checkpoint file or folder (default: the published file in the weights folders)")
    p.add_argument("--external-data", action="store_true", help="keep the weights in FILE.data beside each graph")
    p.set_defaults(func=run)


def _photo_size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 1 or int(h) < 1:
        raise ValueError(f"--photo-size must look like 540x720 (width x height), got {text!r}")
    return int(w), int(h)


def run(args: argparse.Namespace) -> int:
    from . import fail, output_file_problem

    problem = output_file_problem("-o", args.output, (".onnx",))
    if problem:
        return fail("export", problem)
    try:
        from ..mast3r.export import EXPORTABLE

        name = args.matcher.strip().lower().replace("_", "-")
        if name not in EXPORTABLE:
            raise ValueError(f"--matcher {args.matcher!r}: not exportable (exportable: {', '.join(EXPORTABLE)})")
        if args.size is not None and args.size < 16:
            raise ValueError(f"--size {args.size}: must be at least 16 pixels")
        photo = _photo_size(args.photo_size)
        import onnx  # noqa: F401 - the extra, before the model is loaded
        import onnxruntime  # noqa: F401
    except ImportError as e:
        return fail("export", f"{e.name or e} is not installed: pip install 'mapfree[export]'")
    except ValueError as e:
        return fail("export", e)
    from ..mast3r.export import export_matcher
    from ..mast3r.onnxgraph import OPSET
    from ..matching import MissingWeightsError

    try:
        res = export_matcher(
            name,
            args.output,
            args.size,
            photo,
            args.weights,
            True if args.external_data else None,
            progress=lambda line: print(f"mapfree export: {line}", file=sys.stderr, flush=True),
        )
    except (MissingWeightsError, KeyError, ValueError) as e:
        return fail("export", e)
    h, w = res.info.input_hw
    print(
        f"{name}: wrote {', '.join(str(f) for f in res.files)} ({res.bytes / 2**20:.1f} MiB; opset {OPSET}, float32, "
        f"input {w}x{h}, dynamic batch; checked by onnx.checker)"
    )
    return 0

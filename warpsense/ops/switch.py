"""Named fused Warp ops that a context turns back into their torch forms (the benchmarks' plain-torch baseline, and
A/B runs of one op: tools/device/ab.py)."""

from __future__ import annotations

import contextlib


class OpSwitch:
    """The fused ops of one part of the system, by name; all on unless a `torch_ops` context turns some off.

    Args:
        names: the ops' names, as `torch_ops` and `fused` take them.
    """

    def __init__(self, names: tuple[str, ...]):
        self.names = tuple(names)
        self._off: frozenset = frozenset()

    def fused(self, name: str) -> bool:
        """Whether op ``name`` runs fused (not turned off by an enclosing `torch_ops`)."""
        return name not in self._off

    @contextlib.contextmanager
    def torch_ops(self, *names: str):
        """Within this context the named ops (all of them when none is named) run as torch's own ops on every
        device. Unknown names raise a KeyError listing the valid ones."""
        unknown = set(names) - set(self.names)
        if unknown:
            raise KeyError(f"unknown fused op(s) {', '.join(sorted(unknown))}; valid: {', '.join(self.names)}")
        saved, self._off = self._off, self._off | frozenset(names or self.names)
        try:
            yield
        finally:
            self._off = saved

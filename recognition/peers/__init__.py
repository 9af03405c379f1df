"""Peer methods (baselines) behind the core's stage interfaces (DESIGN 6.5).

Each :class:`Peer` replaces exactly one stage of the core and the core runs the others, so a peer is scored
by the same evaluation, on the same trials and images, as the core:

* ``description`` - ``run(scan, params: dict) -> SceneDescription`` (segmentation + classification):
  :mod:`recognition.peers.primitives` (``efficient_ransac`` through CGAL, ``pyransac3d``).
* ``pose`` - ``run(description, scan, model, params: dict, predictor) -> PoseResult``-like:
  :mod:`recognition.peers.registration` (``fpfh_ransac``, ``fgr``: Open3D global registration + ICP).
* ``change`` - ``run(description, scan, model, T_world_sensor, cov, predictor, params: dict) -> ChangeResult``:
  :mod:`recognition.peers.differencing` (``diff_change``, ``c2m_change``, ``m3c2_change``).

:data:`PEERS` holds only the peers whose dependencies import; :data:`MISSING` says, for every peer that did
not register, why (the package that failed to import and its error), so tests and reports can say so.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

STAGES = ("description", "pose", "change")


@dataclass(frozen=True)
class Peer:
    """A peer method behind one stage interface.

    Attributes
    ----------
    name : the suite's method name (e.g. ``"fpfh_ransac"``).
    replaces : ``"description"``, ``"pose"`` or ``"change"``: the one stage it replaces.
    run : the stage function (signatures in the module docstring).
    summary : one line for reports.
    defaults : its default parameters (what ``params`` may override).
    deterministic : False when the underlying library cannot be seeded (then the peer says why in ``summary``).
    """

    name: str
    replaces: str
    run: Callable
    summary: str
    defaults: dict = None  # type: ignore[assignment]
    deterministic: bool = True

    def __post_init__(self):
        if self.replaces not in STAGES:
            raise ValueError(f"replaces must be one of {', '.join(STAGES)}, got {self.replaces!r}")
        if self.defaults is None:
            object.__setattr__(self, "defaults", {})


PEERS: dict[str, Peer] = {}
MISSING: dict[str, str] = {}


def _collect() -> None:
    from recognition.peers import differencing, primitives, registration

    for module in (registration, primitives, differencing):
        for peer in module.available_peers():
            PEERS[peer.name] = peer
        MISSING.update(module.missing_peers())


_collect()

__all__ = ["Peer", "PEERS", "MISSING", "STAGES"]

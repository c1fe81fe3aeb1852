"""The paper's baselines: MLP-CD-CLNN, IN-CP-CLNN and IN-SP-CP (paper-facts.md, "Models compared").

Each replaces one stage of the simulator, never forks it (DESIGN.md):

- **MLP-CD-CLNN** (:class:`MLPCDCLNN`): the CLNN of the physical models
  (learned masses, second moments and potential network, Lagrangian dynamics
  with the true constraints) and the true collision detection; the *impulse*
  stage is :class:`ContactMLP`, a learnable contact model. For every active
  contact an MLP maps the local pre-impact state (positions and velocities of
  the contact's points, the contact Jacobian restricted to them, ``J_C v``,
  the gap over ``dt``, the contact-space inverse inertia ``J_C Mhat^-1 J_C^T`` and a
  learned embedding of the candidate) to an impulse on those points; the
  velocity jump is ``Mhat^-1`` times the summed impulses, so it keeps joints
  and rigid bodies intact.
- **IN-CP-CLNN** (:class:`INCPCLNN`): the same CLNN and detection; the impulse
  stage is :class:`ContactIN`, an interaction network on the body graph
  (bodies and a world node; links, springs, pins and the contacts active at
  this step as edges) that predicts each active contact's impulse in contact
  space, ``f_k: (d,)``, applied as ``v+ = v + Mhat^-1 J_C^T f`` ("contact
  prediction").
- **IN-SP-CP** (:class:`INSPCP`): no physics prior: an interaction network on
  the body graph, with *every* candidate contact as an edge (the network
  predicts whether it acts), maps a state to the next one ("state
  prediction"); the true masses and the external force (gravity) are node
  inputs. Rollouts are repeated steps.

All three take the known structure from the config (geometry, constraints,
contact candidates, ``dt``), work for every task (extended bodies, the
gyroscope, the rope), are batched (edges and contacts padded and masked, no
Python loop over states, edges or contacts), follow the dtype and device of
``z0`` and implement :class:`~diffcontact.learning.models.protocol.DynamicsModel`.
Their options are plain data (``options()``), so they are saved and loaded
like any registered model (:mod:`.storage`).

Example::

    from diffcontact.learning import create_model
    model = create_model("IN-CP-CLNN", "CP3", latent=64)
    traj = model.simulate(z0, steps=10)        # (N, 11, 2, P, dim)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from diffcontact.contact.impulse import ImpulseResult
from diffcontact.contact.models import ContactParams, ContactState
from diffcontact.geometry.base import gather_points
from diffcontact.learning.models.physical import (
    PHYSICS_BETAS,
    PotentialMLP,
    _initial_second_moments,
    hidden_widths,
)
from diffcontact.learning.models.protocol import OptimizerSettings
from diffcontact.learning.models.registry import BASELINE_MODELS
from diffcontact.systems import NonFiniteRolloutError, PhysicalParams, System, load_config
from diffcontact.systems.config import rollout_size_error
from diffcontact.systems.graph import EDGE_KINDS, ENVIRONMENT
from diffcontact.threads import thread_scope

__all__ = [
    "BASELINE_MODELS",
    "INCPCLNN",
    "INSPCP",
    "MLP",
    "MLPCDCLNN",
    "ContactIN",
    "ContactMLP",
    "InteractionNetwork",
]

DEFAULT_POTENTIAL_HIDDEN = (256, 256, 256)
DEFAULT_CONTACT_HIDDEN = (256, 256)
DEFAULT_IN_HIDDEN = (128, 128)
DEFAULT_LATENT = 128
DEFAULT_EMBEDDING = 8
N_KINDS = len(EDGE_KINDS)
_CONTACT_KIND = EDGE_KINDS.index("contact")


# ----------------------------------------------------------------------------- options
def _integer(name: str, value: Any, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


# ----------------------------------------------------------------------------- blocks
class MLP(nn.Module):
    """A plain MLP ``(..., n_in) -> (..., n_out)`` with SiLU hidden activations.

    The weights are cast to the input's dtype and device when they differ (a
    no-op when they match), so a model trained in float32 rolls out in
    float64. The output layer starts ``out_gain`` times smaller than the
    default initialisation, so a fresh network predicts small corrections.

    Args:
        n_in, n_out: input and output sizes.
        hidden: hidden widths (may be empty: one linear layer).
        out_gain: scale of the output layer's initial weights and bias.
    """

    def __init__(self, n_in: int, hidden: Sequence[int], n_out: int, out_gain: float = 1.0) -> None:
        super().__init__()
        widths = [int(n_in), *(int(h) for h in hidden), int(n_out)]
        self.layers = nn.ModuleList(
            nn.Linear(widths[i], widths[i + 1]) for i in range(len(widths) - 1)
        )
        if out_gain != 1.0:
            with torch.no_grad():
                self.layers[-1].weight.mul_(out_gain)
                self.layers[-1].bias.mul_(out_gain)

    def forward(self, h: Tensor) -> Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            w, b = layer.weight, layer.bias
            if w.dtype != h.dtype or w.device != h.device:
                w, b = w.to(h), b.to(h)
            h = F.linear(h, w, b)
            if i < last:
                h = F.silu(h)
        return h


class InteractionNetwork(nn.Module):
    """Encode-process-decode interaction network on a batch of graphs (Battaglia et al. 2016).

    Nodes and edges are encoded to ``latent`` vectors; each of ``steps``
    rounds updates every edge from itself and its two nodes (residual), sums
    the messages of the real edges into their receivers (``scatter_add``:
    no loop over edges or graphs) and updates every node from itself and the
    sum (residual). The caller decodes what it needs from the result.

    Args:
        node_in, edge_in: sizes of the node and edge features.
        latent: size of the latent vectors.
        hidden: hidden widths of every MLP.
        steps: rounds of message passing (>= 1).
    """

    def __init__(
        self, node_in: int, edge_in: int, latent: int, hidden: Sequence[int], steps: int
    ) -> None:
        super().__init__()
        self.node_encoder = MLP(node_in, hidden, latent)
        self.edge_encoder = MLP(edge_in, hidden, latent)
        self.edge_updates = nn.ModuleList(MLP(3 * latent, hidden, latent) for _ in range(steps))
        self.node_updates = nn.ModuleList(MLP(2 * latent, hidden, latent) for _ in range(steps))

    def forward(
        self,
        nodes: Tensor,
        edges: Tensor,
        senders: Tensor,
        receivers: Tensor,
        mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        """Run the network.

        Args:
            nodes: ``(n, V, node_in)``.
            edges: ``(n, E, edge_in)``.
            senders, receivers: ``(n, E)`` long, node indices of each edge.
            mask: ``(n, E)`` bool, the real edges (``None``: all); the others
                send nothing (their latents are computed but meaningless).

        Returns:
            ``(h, e)``: node latents ``(n, V, latent)`` and edge latents ``(n, E, latent)``.
        """
        h = self.node_encoder(nodes)
        e = self.edge_encoder(edges)
        L = h.shape[-1]
        send = senders.unsqueeze(-1).expand(*senders.shape, L)
        recv = receivers.unsqueeze(-1).expand(*receivers.shape, L)
        for edge_fn, node_fn in zip(self.edge_updates, self.node_updates, strict=True):
            e = e + edge_fn(torch.cat([e, h.gather(1, send), h.gather(1, recv)], dim=-1))
            msg = e if mask is None else torch.where(mask.unsqueeze(-1), e, torch.zeros_like(e))
            agg = torch.zeros_like(h).scatter_add(1, recv, msg)
            h = h + node_fn(torch.cat([h, agg], dim=-1))
        return h, e


# ----------------------------------------------------------------------------- the graph
class _GraphTables(nn.Module):
    """Static index tables of a system's body graph, as (non-persistent) buffers.

    ``B`` bodies plus a world node (index ``B``); ``Pb`` the most points of a
    body; ``K`` candidate contacts, ``Pe`` the most points of a contact;
    ``Es`` structural edges (links, springs, pins).

    Buffers: ``body_points (B, Pb)``, ``body_point_mask (B, Pb)``,
    ``point_body (P,)``, ``point_slot (P,)``, ``centres (B,)``, ``edge_points (K, Pe)``,
    ``edge_point_mask (K, Pe)``,
    ``slot_of_point (K, P)`` (a point's slot in ``edge_points[k]``, or ``Pe``),
    ``contact_bodies (K, 2)``, ``struct_bodies (Es, 2)``, ``struct_kind (Es,)``.
    Float constants (float64, cast on use by :meth:`constant`): ``radius (B,)``
    (0 where a body has none) and those added with :meth:`add_constant`.
    """

    def __init__(self, system: System) -> None:
        super().__init__()
        graph = system.body_graph()
        bodies, P = graph.bodies, graph.n_points
        B, K = len(bodies), system.n_contacts
        self.n_bodies, self.n_points, self.dim, self.d = B, P, system.dim, system.d
        self.dt = system.dt
        Pb = max(len(b.points) for b in bodies)
        body_points = torch.zeros(B, Pb, dtype=torch.long)
        body_point_mask = torch.zeros(B, Pb, dtype=torch.bool)
        point_body = torch.zeros(P, dtype=torch.long)
        point_slot = torch.zeros(P, dtype=torch.long)
        for body in bodies:
            for s, p in enumerate(body.points):
                body_points[body.index, s], body_point_mask[body.index, s] = p, True
                point_body[p], point_slot[p] = body.index, s
        contacts = graph.edges_of("contact")
        assert [e.contact for e in contacts] == list(range(K))
        Pe = max(len(e.points) for e in contacts)
        edge_points = torch.zeros(K, Pe, dtype=torch.long)
        edge_point_mask = torch.zeros(K, Pe, dtype=torch.bool)
        slot_of_point = torch.full((K, P), Pe, dtype=torch.long)
        for k, edge in enumerate(contacts):
            for s, p in enumerate(edge.points):
                edge_points[k, s], edge_point_mask[k, s], slot_of_point[k, p] = p, True, s

        def node(b: int) -> int:
            return B if b == ENVIRONMENT else b

        structural = [e for e in graph.edges if e.kind != "contact"]
        self.n_struct, self.Pb, self.Pe = len(structural), Pb, Pe
        buffers = {
            "body_points": body_points,
            "body_point_mask": body_point_mask,
            "point_body": point_body,
            "point_slot": point_slot,
            "centres": torch.tensor([b.points[0] for b in bodies], dtype=torch.long),
            "edge_points": edge_points,
            "edge_point_mask": edge_point_mask,
            "slot_of_point": slot_of_point,
            "contact_bodies": torch.tensor(
                [[node(i) for i in e.bodies] for e in contacts], dtype=torch.long
            ).reshape(K, 2),
            "struct_bodies": torch.tensor(
                [[node(i) for i in e.bodies] for e in structural], dtype=torch.long
            ).reshape(-1, 2),
            "struct_kind": torch.tensor(
                [EDGE_KINDS.index(e.kind) for e in structural], dtype=torch.long
            ),
        }
        for name, value in buffers.items():
            self.register_buffer(name, value, persistent=False)
        # known float constants stay float64 (model.to(float32) must not round them) and
        # are cast to the input's dtype and device on use
        self._constants: dict[str, Tensor] = {
            "radius": torch.tensor([b.radius or 0.0 for b in bodies], dtype=torch.float64)
        }
        self._cache: dict[tuple[str, torch.dtype, torch.device], Tensor] = {}

    def add_constant(self, name: str, value: Tensor) -> None:
        """Register a float64 constant for :meth:`constant`."""
        self._constants[name] = value.detach().to(torch.float64).cpu()

    def constant(self, name: str, like: Tensor) -> Tensor:
        """The constant ``name`` in ``like``'s dtype and on its device (cached)."""
        key = (name, like.dtype, like.device)
        if key not in self._cache:
            self._cache[key] = self._constants[name].to(dtype=like.dtype, device=like.device)
        return self._cache[key]

    # features ---------------------------------------------------------------
    def body_states(self, x: Tensor, v: Tensor) -> Tensor:
        """``(n, B, 2 * Pb * dim)``: positions then velocities of each body's points (padded 0)."""
        n = x.shape[0]
        idx = self.body_points.expand(n, *self.body_points.shape)
        keep = self.body_point_mask[..., None]
        xb = torch.where(
            keep, gather_points(x, idx), torch.zeros((), dtype=x.dtype, device=x.device)
        )
        vb = torch.where(
            keep, gather_points(v, idx), torch.zeros((), dtype=x.dtype, device=x.device)
        )
        return torch.cat([xb.flatten(-2), vb.flatten(-2)], dim=-1)

    def nodes(self, x: Tensor, v: Tensor, extra: str | None = None) -> Tensor:
        """Node features ``(n, B + 1, F)``: body states, radius, the constant ``extra``
        ``(B, F')`` if named, world flag.

        The world node (last) has zero features and flag 1.
        """
        n = x.shape[0]
        radius = self.constant("radius", x)
        parts = [self.body_states(x, v), radius.expand(n, -1).unsqueeze(-1)]
        if extra is not None:
            value = self.constant(extra, x)
            parts.append(value.expand(n, *value.shape))
        body = torch.cat(parts, dim=-1)
        body = torch.cat([body, body.new_zeros(n, body.shape[1], 1)], dim=-1)
        world = body.new_zeros(n, 1, body.shape[-1])
        world[..., -1] = 1.0
        return torch.cat([body, world], dim=1)

    def centre_states(self, x: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """Centres of mass and their velocities ``(n, B + 1, dim)`` (the world at rest at 0)."""
        pad = x.new_zeros(x.shape[0], 1, x.shape[-1])
        xc = torch.cat([x[:, self.centres], pad], dim=1)
        vc = torch.cat([v[:, self.centres], pad], dim=1)
        return xc, vc

    def restrict(self, J: Tensor, idx: Tensor) -> Tensor:
        """Dense Jacobian rows ``(n, Ka, d, P, dim)`` -> ``(n, Ka, d, Pe, dim)`` on each
        contact's points (zero on padded slots)."""
        n, Ka, d, _, dim = J.shape
        pts = self.edge_points[idx]  # (n, Ka, Pe)
        index = pts[:, :, None, :, None].expand(n, Ka, d, self.Pe, dim)
        J_e = J.gather(3, index)
        keep = self.edge_point_mask[idx][:, :, None, :, None]
        return torch.where(keep, J_e, torch.zeros((), dtype=J.dtype, device=J.device))

    def restrict_sparse(self, points: Tensor, values: Tensor, idx: Tensor) -> Tensor:
        """A :class:`~diffcontact.geometry.SparseJacobian` of candidates ``idx: (n, Ka)``
        -> dense rows on each contact's points ``(n, Ka, d, Pe, dim)``."""
        n, Ka, d, m, dim = values.shape
        slots = self.slot_of_point[idx.unsqueeze(-1), points]  # (n, Ka, m), Pe = not a point
        index = slots[:, :, None, :, None].expand(n, Ka, d, m, dim)
        out = values.new_zeros(n, Ka, d, self.Pe + 1, dim).scatter_add(3, index, values)
        return out[..., : self.Pe, :]

    def directed(
        self, bodies: Tensor, shared: Tensor, xc: Tensor, vc: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Both directions of undirected edges, with their features.

        Args:
            bodies: ``(n, E, 2)`` long, node indices ``(i, j)`` of each edge.
            shared: ``(n, E, F)`` features of the edge.
            xc, vc: ``(n, B + 1, dim)`` node centres and velocities.

        Returns:
            ``senders, receivers: (n, 2E)`` (first ``j -> i``, then ``i -> j``) and
            features ``(n, 2E, F + 1 + 2 dim)``: shared, direction (+-1), and the
            receiver's centre and velocity relative to the sender's.
        """
        i, j = bodies[..., 0], bodies[..., 1]
        senders, receivers = torch.cat([j, i], dim=1), torch.cat([i, j], dim=1)
        dim = xc.shape[-1]
        rel_x = xc.gather(1, receivers[..., None].expand(-1, -1, dim)) - xc.gather(
            1, senders[..., None].expand(-1, -1, dim)
        )
        rel_v = vc.gather(1, receivers[..., None].expand(-1, -1, dim)) - vc.gather(
            1, senders[..., None].expand(-1, -1, dim)
        )
        n, E = shared.shape[:2]
        sign = shared.new_ones(n, E, 1)
        feats = torch.cat([torch.cat([shared, sign], -1), torch.cat([shared, -sign], -1)], dim=1)
        return senders, receivers, torch.cat([feats, rel_x, rel_v], dim=-1)

    def kind_onehot(self, kinds: Tensor, like: Tensor) -> Tensor:
        """``(..., 4)`` one-hot edge kinds (link, spring, pin, contact)."""
        return F.one_hot(kinds, N_KINDS).to(like)


def _contact_space_inertia(J_C: Tensor, Mhat_inv: Tensor, n: int, Ka: int, d: int) -> Tensor:
    """Diagonal blocks ``(n, Ka, d, d)`` of ``A = J_C Mhat^-1 J_C^T`` (one per contact)."""
    JM = (J_C @ Mhat_inv).reshape(n, Ka, d, -1)
    return torch.einsum("nkad,nkbd->nkab", JM, J_C.reshape(n, Ka, d, -1))


def _contact_features(
    tables: _GraphTables,
    J_C: Tensor,
    Mhat_inv: Tensor,
    v: Tensor,
    state: ContactState,
    d: int,
    dt: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """Local features of the padded contacts of one step.

    Returns:
        ``features (n, Ka, F)``: the contact's points' positions and velocities
        ``(Pe, dim)`` each, its Jacobian on them ``(d, Pe, dim)``, ``J_C v (d)``,
        its gap divided by ``dt`` (a velocity, like ``J_C v``: penetrating within a step
        is ``gap / dt + v_C,n < 0``; differentiable in ``x``) and ``A_kk (d, d)``; the points'
        indices ``(n, Ka, Pe)`` and their mask ``(n, Ka, Pe)``.
    """
    x, idx = state.x, state.contact_index
    n, Ka = idx.shape
    P, dim = x.shape[-2:]
    vp = v.reshape(n, P, dim)
    pts, keep = tables.edge_points[idx], tables.edge_point_mask[idx]
    zero = torch.zeros((), dtype=x.dtype, device=x.device)
    x_e = torch.where(keep[..., None], gather_points(x, pts), zero)
    v_e = torch.where(keep[..., None], gather_points(vp, pts), zero)
    J_e = tables.restrict(J_C.reshape(n, Ka, d, P, dim), idx)
    v_C = (J_C @ v.unsqueeze(-1)).reshape(n, Ka, d)
    gap = state.geometry.gaps(x).gather(-1, idx).unsqueeze(-1) / dt
    A = _contact_space_inertia(J_C, Mhat_inv, n, Ka, d)
    feats = torch.cat(
        [x_e.flatten(2), v_e.flatten(2), J_e.flatten(2), v_C, gap, A.flatten(2)], dim=-1
    )
    return feats, pts, keep


# ----------------------------------------------------------------------------- contact models
class ContactMLP(nn.Module):
    """MLP-CD-CLNN's impulse stage: a learnable contact model (``resolve``).

    For each active contact ``k`` the MLP reads its local pre-impact state
    (see :func:`_contact_features`: positions and velocities of its points,
    its Jacobian on them, ``J_C v``, the gap over ``dt``, ``A_kk``) and a learned
    embedding of the candidate (so contacts with different, unknown
    properties can differ) and outputs an impulse ``p_k: (Pe, dim)`` on the
    contact's points. The velocity jump is ``Mhat^-1 sum_k p_k``; padded
    contacts contribute exactly zero.

    Args:
        tables: the system's graph tables.
        hidden: hidden widths of the MLP.
        embedding: size of the per-candidate embedding (0: none).
    """

    needs_contact_state = True

    def __init__(self, tables: _GraphTables, hidden: Sequence[int], embedding: int) -> None:
        super().__init__()
        self.tables = tables
        t = tables
        K = t.slot_of_point.shape[0]
        n_in = 2 * t.Pe * t.dim + t.d * t.Pe * t.dim + t.d + 1 + t.d * t.d + embedding
        self.embedding = nn.Parameter(0.1 * torch.randn(K, embedding)) if embedding else None
        self.net = MLP(n_in, hidden, t.Pe * t.dim, out_gain=0.1)

    def resolve(
        self,
        J_C: Tensor,
        Mhat_inv: Tensor,
        v: Tensor,
        params: ContactParams,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: Any = None,
        state: ContactState | None = None,
    ) -> ImpulseResult:
        """The contact-model protocol (:class:`~diffcontact.contact.ContactModel`).

        ``params``, ``v_C_star`` and ``settings`` are not used; ``state`` is
        required. ``f_c`` and ``f_r`` are zero (the impulses are not in contact space).
        """
        if state is None:
            raise ValueError("ContactMLP.resolve needs state= (System.simulate passes it)")
        t = self.tables
        feats, pts, keep = _contact_features(t, J_C, Mhat_inv, v, state, d, t.dt)
        n, Ka = active.shape
        if self.embedding is not None:
            emb = self.embedding.to(feats)[state.contact_index]
            feats = torch.cat([feats, emb], dim=-1)
        dim = self.tables.dim
        p_e = self.net(feats).reshape(n, Ka, self.tables.Pe, dim)
        keep = keep & active.unsqueeze(-1)
        p_e = torch.where(keep[..., None], p_e, torch.zeros((), dtype=v.dtype, device=v.device))
        index = pts.reshape(n, -1, 1).expand(n, Ka * self.tables.Pe, dim)
        P = self.tables.n_points
        p = v.new_zeros(n, P, dim).scatter_add(1, index, p_e.reshape(n, -1, dim))
        v_plus = v + (Mhat_inv @ p.reshape(n, -1, 1)).squeeze(-1)
        zeros = v.new_zeros(n, Ka * d)
        return ImpulseResult(v_plus=v_plus, f_c=zeros, f_r=zeros)


class ContactIN(nn.Module):
    """IN-CP-CLNN's impulse stage: an interaction network on the body graph (``resolve``).

    Nodes: the bodies (positions and velocities of their points, radius) and
    a world node. Edges, both directions: the structural ones (links,
    springs, pins: kind, relative centre position and velocity) and the
    contacts active at this step (also their local features, as
    :class:`ContactMLP`'s, without an embedding). After the message passing,
    each active contact's two directed edge latents and the latents of its two
    nodes are decoded to its contact-space impulse ``f_k: (d,)``;
    ``v+ = v + Mhat^-1 J_C^T f``.

    Args:
        tables: the system's graph tables.
        latent, hidden, steps: see :class:`InteractionNetwork`.
    """

    needs_contact_state = True

    def __init__(
        self, tables: _GraphTables, latent: int, hidden: Sequence[int], steps: int
    ) -> None:
        super().__init__()
        self.tables = t = tables
        self.n_contact = 2 * t.Pe * t.dim + t.d * t.Pe * t.dim + t.d + 1 + t.d * t.d
        node_in = 2 * t.Pb * t.dim + 2
        edge_in = N_KINDS + self.n_contact + 1 + 2 * t.dim
        self.network = InteractionNetwork(node_in, edge_in, latent, hidden, steps)
        self.decoder = MLP(4 * latent, hidden, t.d, out_gain=0.1)

    def resolve(
        self,
        J_C: Tensor,
        Mhat_inv: Tensor,
        v: Tensor,
        params: ContactParams,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: Any = None,
        state: ContactState | None = None,
    ) -> ImpulseResult:
        """The contact-model protocol; returns the predicted impulses as ``f_c``
        (``f_r`` is zero). ``params``, ``v_C_star``, ``settings`` are not used."""
        if state is None:
            raise ValueError("ContactIN.resolve needs state= (System.simulate passes it)")
        t = self.tables
        x = state.x
        n, Ka = active.shape
        vp = v.reshape(n, t.n_points, t.dim)
        feats, _, _ = _contact_features(t, J_C, Mhat_inv, v, state, d, t.dt)
        Es = t.n_struct
        struct = torch.cat(
            [t.kind_onehot(t.struct_kind, x), x.new_zeros(Es, self.n_contact)], dim=-1
        ).expand(n, Es, -1)
        kind = t.kind_onehot(torch.full_like(state.contact_index, _CONTACT_KIND), x)
        shared = torch.cat([struct, torch.cat([kind, feats], dim=-1)], dim=1)
        bodies = torch.cat(
            [t.struct_bodies.expand(n, Es, 2), t.contact_bodies[state.contact_index]], dim=1
        )
        xc, vc = t.centre_states(x, vp)
        senders, receivers, edges = t.directed(bodies, shared, xc, vc)
        real = torch.cat([active.new_ones(n, Es), active], dim=1)
        mask = torch.cat([real, real], dim=1)
        h, e = self.network(t.nodes(x, vp), edges, senders, receivers, mask)
        E = Es + Ka
        ends = bodies[:, Es:]  # (n, Ka, 2) the contacts' nodes
        L = h.shape[-1]
        h_ends = h.gather(1, ends.reshape(n, -1, 1).expand(n, 2 * Ka, L)).reshape(n, Ka, 2 * L)
        f = self.decoder(torch.cat([e[:, Es:E], e[:, E + Es :], h_ends], dim=-1))
        f = torch.where(active.unsqueeze(-1), f, torch.zeros((), dtype=v.dtype, device=v.device))
        f = f.reshape(n, Ka * d)
        impulse = (J_C.transpose(-1, -2) @ f.unsqueeze(-1)).squeeze(-1)
        v_plus = v + (Mhat_inv @ impulse.unsqueeze(-1)).squeeze(-1)
        return ImpulseResult(v_plus=v_plus, f_c=f, f_r=torch.zeros_like(f))


# ----------------------------------------------------------------------------- CLNN baselines
class _CLNNWithContactNet(nn.Module):
    """The CLNN of the physical models with a learnable contact model (shared base).

    Parameters: ``log_mass_scale ()``, ``log_mass_rel (B,)``,
    ``log_second_moments (B, dim)`` (rigid bodies), the potential MLP
    (``potential``) and the contact network (``contact_net``). Masses,
    second moments and the potential are parameterised and initialised as in
    :class:`~diffcontact.learning.models.physical.LearnedModel`.
    """

    model_name: str
    dynamics = "lagrangian"

    def _build_clnn(self, config: Any, hidden: Any) -> None:
        self.system = System(load_config(config))
        self.hidden = hidden_widths("hidden", hidden)
        system = self.system
        self.log_mass_scale = nn.Parameter(torch.zeros(()))
        self.log_mass_rel = nn.Parameter(torch.zeros(system.n_bodies))
        if system.second_moments is not None:
            init = _initial_second_moments(system.config, tuple(system.second_moments.shape))
            self.log_second_moments: nn.Parameter | None = nn.Parameter(init.log())
        else:
            self.log_second_moments = None
        self.potential = PotentialMLP(system.n_points * system.dim, self.hidden)
        self.tables = _GraphTables(system)

    # structure -------------------------------------------------------------------
    @property
    def config(self) -> Any:
        """The validated config of the known structure."""
        return self.system.config

    @property
    def dt(self) -> float:
        return self.system.dt

    @property
    def default_steps(self) -> int:
        return self.system.default_steps

    @property
    def state_shape(self) -> tuple[int, int, int]:
        return self.system.state_shape

    @property
    def contact_model(self) -> nn.Module:
        """The learnable contact model (what ``System.simulate`` is given)."""
        return self.contact_net

    def extra_repr(self) -> str:
        return f"model={self.model_name!r}, system={self.system.name!r}"

    # parameters ------------------------------------------------------------------
    def mass(self) -> Tensor:
        """``(B,)`` learned masses."""
        return (self.log_mass_scale + self.log_mass_rel).exp()

    def second_moments(self) -> Tensor | None:
        """``(B, dim)`` learned second moments per unit mass, or ``None``."""
        return None if self.log_second_moments is None else self.log_second_moments.exp()

    def physical_params(self) -> PhysicalParams:
        """The learned masses, second moments and potential as :class:`PhysicalParams`.

        Gravity (and the rope's springs) are zero: the potential network carries
        the whole potential. ``mu`` and ``cor`` are zero: the contact network
        does not read them.
        """
        ref = self.log_mass_rel
        zero = torch.zeros((), dtype=ref.dtype, device=ref.device)
        base = self.system.parameters()
        K = self.system.n_contacts
        return base.replace(
            mass=self.mass(),
            second_moments=self.second_moments(),
            mu=zero.expand(K),
            cor=zero.expand(K),
            gravity=zero,
            stiffness=None if base.stiffness is None else zero,
            potential=self.potential,
        )

    def physical_parameters(self) -> list[nn.Parameter]:
        """``log_mass_scale``, ``log_mass_rel`` and ``log_second_moments`` (if any)."""
        names = ("log_mass_scale", "log_mass_rel", "log_second_moments")
        return [p for n in names if isinstance(p := getattr(self, n, None), nn.Parameter)]

    def learned_parameters(self) -> dict[str, Any]:
        """``mass``, ``mass_ratios``, ``second_moments`` as plain numbers; ``mu``,
        ``cor`` and ``eps`` are ``None`` (the contact network has none)."""
        with torch.no_grad():
            mass = self.mass().double().cpu()
            s = self.second_moments()
            return {
                "mass": mass.tolist(),
                "mass_ratios": (mass / mass[0]).tolist(),
                "second_moments": None if s is None else s.double().cpu().tolist(),
                "mu": None,
                "cor": None,
                "eps": None,
            }

    # protocol --------------------------------------------------------------------
    def param_groups(self, settings: OptimizerSettings) -> list[dict[str, Any]]:
        """``network`` (potential and contact networks: ``lr``, weight decay) and
        ``physical`` (masses, second moments: ``physics_lr``, no weight decay)."""
        physical = [p for p in self.physical_parameters() if p.requires_grad]
        chosen = {id(p) for p in physical}
        network = [p for p in self.parameters() if p.requires_grad and id(p) not in chosen]
        return [
            {"name": "network", "params": network, "lr": settings.lr,
             "weight_decay": settings.weight_decay},
            {"name": "physical", "params": physical, "lr": settings.physics_lr,
             "weight_decay": 0.0, "betas": PHYSICS_BETAS},
        ]  # fmt: skip

    def metrics(self) -> dict[str, float]:
        """``param/mass_0`` and ``param/mass_ratio_i`` (i >= 1)."""
        params = self.learned_parameters()
        out = {"param/mass_0": params["mass"][0]}
        for i, r in enumerate(params["mass_ratios"][1:], start=1):
            out[f"param/mass_ratio_{i}"] = r
        return out

    def simulate(
        self,
        z0: Tensor,
        steps: int | None = None,
        *,
        check_overlap: bool = True,
        solver_settings: Any = None,
        progress: bool = False,
        penetration_fraction: float | None = None,
        on_tunnelling: str = "warn",
        threads: int | str | None = "auto",
    ) -> Tensor:
        """``(N, 2, P, dim)`` -> ``(N, steps + 1, 2, P, dim)``: ``System.simulate`` with the
        learned parameters and the contact network as the contact model.

        Differentiable with respect to every parameter and ``z0``; the rollout
        runs in ``z0``'s dtype and on its device. ``solver_settings`` is not
        used (no cone QP); the other options are ``System.simulate``'s.
        """
        return self.system.simulate(
            z0,
            steps,
            params=self.physical_params(),
            contact_model=self.contact_net,
            dynamics=self.dynamics,
            progress=progress,
            penetration_fraction=penetration_fraction,
            check_overlap=check_overlap,
            on_tunnelling=on_tunnelling,
            threads=threads,
        )

    def forward(self, z0: Tensor, steps: int | None = None, **kwargs: Any) -> Tensor:
        """Same as :meth:`simulate`."""
        return self.simulate(z0, steps, **kwargs)

    def energy(self, z: Tensor) -> Tensor:
        """Learned energy ``0.5 v^T M v + V(x)``: ``(..., 2, P, dim) -> (...)``."""
        return self.system.energy(z, params=self.physical_params())


class MLPCDCLNN(_CLNNWithContactNet):
    """MLP-CD-CLNN: CLNN + true collision detection + :class:`ContactMLP`.

    Args:
        config: the known structure (task name, path, dict or config).
        hidden: hidden widths of the potential MLP (default 256, 256, 256).
        contact_hidden: hidden widths of the contact MLP (default 256, 256).
        embedding: size of the learned per-candidate embedding (default 8; 0: none).
    """

    model_name = "MLP-CD-CLNN"

    def __init__(
        self,
        config: Any,
        *,
        hidden: Any = DEFAULT_POTENTIAL_HIDDEN,
        contact_hidden: Any = DEFAULT_CONTACT_HIDDEN,
        embedding: Any = DEFAULT_EMBEDDING,
    ) -> None:
        super().__init__()
        self._build_clnn(config, hidden)
        self.contact_hidden = hidden_widths("contact_hidden", contact_hidden)
        self.embedding = _integer("embedding", embedding, 0)
        self.contact_net = ContactMLP(self.tables, self.contact_hidden, self.embedding)

    def options(self) -> dict[str, Any]:
        """Constructor options as plain data."""
        return {
            "hidden": list(self.hidden),
            "contact_hidden": list(self.contact_hidden),
            "embedding": self.embedding,
        }


class INCPCLNN(_CLNNWithContactNet):
    """IN-CP-CLNN: CLNN + true collision detection + :class:`ContactIN`.

    Args:
        config: the known structure.
        hidden: hidden widths of the potential MLP (default 256, 256, 256).
        latent: latent size of the interaction network (default 128).
        contact_hidden: hidden widths of its MLPs (default 128, 128).
        message_steps: rounds of message passing (default 1).
    """

    model_name = "IN-CP-CLNN"

    def __init__(
        self,
        config: Any,
        *,
        hidden: Any = DEFAULT_POTENTIAL_HIDDEN,
        latent: Any = DEFAULT_LATENT,
        contact_hidden: Any = DEFAULT_IN_HIDDEN,
        message_steps: Any = 1,
    ) -> None:
        super().__init__()
        self._build_clnn(config, hidden)
        self.latent = _integer("latent", latent, 1)
        self.contact_hidden = hidden_widths("contact_hidden", contact_hidden)
        self.message_steps = _integer("message_steps", message_steps, 1)
        self.contact_net = ContactIN(
            self.tables, self.latent, self.contact_hidden, self.message_steps
        )

    def options(self) -> dict[str, Any]:
        """Constructor options as plain data."""
        return {
            "hidden": list(self.hidden),
            "latent": self.latent,
            "contact_hidden": list(self.contact_hidden),
            "message_steps": self.message_steps,
        }


# ----------------------------------------------------------------------------- IN-SP-CP
class INSPCP(nn.Module):
    """IN-SP-CP: an interaction network that predicts the next state (no physics prior).

    Graph: the bodies and a world node; edges (both directions) are the
    structural ones and *every* candidate contact (contact prediction: the
    network decides from the features whether a contact acts). Node features:
    positions and velocities of the body's points, radius, the true log mass
    and the true external force (gravity ``m g``) from the config. Edge
    features: kind, relative centre position and velocity, and for contacts
    ``J_C v``, the gap over ``dt`` and the contact Jacobian on the contact's points. The
    decoder gives per point ``(dx, dv)``; the step is
    ``v' = v + dv``, ``x' = x + dt (v' + dx)`` (with zero output: free flight).

    Args:
        config: the known structure, true masses and gravity.
        hidden: hidden widths of the network's MLPs (default 128, 128).
        latent: latent size (default 128).
        message_steps: rounds of message passing (default 2: a contact's
            effect reaches the neighbours of its bodies within one step).

    The network has no parameters but its weights: ``param_groups`` has one
    ``network`` group and ``metrics`` is empty.
    """

    model_name = "IN-SP-CP"

    def __init__(
        self,
        config: Any,
        *,
        hidden: Any = DEFAULT_IN_HIDDEN,
        latent: Any = DEFAULT_LATENT,
        message_steps: Any = 2,
    ) -> None:
        super().__init__()
        self.system = system = System(load_config(config))
        self.hidden = hidden_widths("hidden", hidden)
        self.latent = _integer("latent", latent, 1)
        self.message_steps = _integer("message_steps", message_steps, 1)
        self.tables = t = _GraphTables(system)
        g = torch.zeros(system.dim, dtype=torch.float64)
        g[1 if system.dim == 2 else 2] = -float(system.gravity)
        force = system.mass[:, None] * g  # (B, dim)
        t.add_constant("known", torch.cat([system.mass.log()[:, None], force], -1))
        self.register_buffer(
            "candidates", torch.arange(system.n_contacts, dtype=torch.long), persistent=False
        )
        n_contact = t.d + 1 + t.d * t.Pe * t.dim
        self.n_contact = n_contact
        node_in = 2 * t.Pb * t.dim + 1 + (1 + t.dim) + 1
        edge_in = N_KINDS + n_contact + 1 + 2 * t.dim
        self.network = InteractionNetwork(
            node_in, edge_in, self.latent, self.hidden, self.message_steps
        )
        self.decoder = MLP(self.latent, self.hidden, t.Pb * 2 * t.dim, out_gain=0.1)

    @property
    def config(self) -> Any:
        """The validated config of the known structure."""
        return self.system.config

    @property
    def dt(self) -> float:
        return self.system.dt

    @property
    def default_steps(self) -> int:
        return self.system.default_steps

    @property
    def state_shape(self) -> tuple[int, int, int]:
        return self.system.state_shape

    def extra_repr(self) -> str:
        return f"model={self.model_name!r}, system={self.system.name!r}"

    def options(self) -> dict[str, Any]:
        """Constructor options as plain data."""
        return {
            "hidden": list(self.hidden),
            "latent": self.latent,
            "message_steps": self.message_steps,
        }

    def param_groups(self, settings: OptimizerSettings) -> list[dict[str, Any]]:
        """One group, ``network`` (``lr``, weight decay)."""
        params = [p for p in self.parameters() if p.requires_grad]
        return [{"name": "network", "params": params, "lr": settings.lr,
                 "weight_decay": settings.weight_decay}]  # fmt: skip

    def metrics(self) -> dict[str, float]:
        """Empty: the model has no physical parameters."""
        return {}

    def step(self, z: Tensor) -> Tensor:
        """One predicted step ``(N, 2, P, dim) -> (N, 2, P, dim)``."""
        t = self.tables
        x, v = z[:, 0], z[:, 1]
        n, K = x.shape[0], self.system.n_contacts
        geometry = self.system._static_on(x.device)[0]
        idx = self.candidates.expand(n, K)
        jac = geometry.jacobian_sparse(x, idx)
        J_e = t.restrict_sparse(jac.points, jac.values, idx)  # (n, K, d, Pe, dim)
        pts, keep = t.edge_points.expand(n, -1, -1), t.edge_point_mask
        v_e = torch.where(
            keep[..., None], gather_points(v, pts), torch.zeros((), dtype=x.dtype, device=x.device)
        )
        v_C = (J_e * v_e.unsqueeze(2)).sum((-1, -2))  # (n, K, d)
        gap = geometry.gaps(x).unsqueeze(-1) / self.dt  # a velocity, like v_C
        Es = t.n_struct
        struct = torch.cat(
            [t.kind_onehot(t.struct_kind, x), x.new_zeros(Es, self.n_contact)], dim=-1
        ).expand(n, Es, -1)
        kind = t.kind_onehot(idx.new_full((n, K), _CONTACT_KIND), x)
        contact = torch.cat([kind, v_C, gap, J_e.flatten(2)], dim=-1)
        shared = torch.cat([struct, contact], dim=1)
        bodies = torch.cat([t.struct_bodies, t.contact_bodies], dim=0).expand(n, -1, -1)
        xc, vc = t.centre_states(x, v)
        senders, receivers, edges = t.directed(bodies, shared, xc, vc)
        h, _ = self.network(t.nodes(x, v, "known"), edges, senders, receivers)
        out = self.decoder(h[:, : t.n_bodies]).reshape(n, t.n_bodies, t.Pb, 2, t.dim)
        out = out[:, t.point_body, t.point_slot]  # (n, P, 2, dim)
        v1 = v + out[..., 1, :]
        x1 = x + self.dt * (v1 + out[..., 0, :])
        return torch.stack([x1, v1], dim=1)

    def simulate(
        self,
        z0: Tensor,
        steps: int | None = None,
        *,
        check_overlap: bool = True,
        solver_settings: Any = None,
        progress: bool = False,
        threads: int | str | None = "auto",
    ) -> Tensor:
        """``(N, 2, P, dim)`` -> ``(N, steps + 1, 2, P, dim)`` by repeated :meth:`step`.

        Differentiable with respect to the weights and ``z0``; runs in ``z0``'s
        dtype and on its device. ``solver_settings`` is not used; ``threads`` is
        ``System.simulate``'s.

        Raises:
            ValueError: a bad ``z0`` or ``steps``, overlapping bodies in ``z0``
                (with ``check_overlap``), or a rollout that became NaN or infinite.
        """
        system = self.system
        system._check_state(z0, "z0")
        if steps is None:
            steps = system.default_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 0:
            raise ValueError(f"steps must be a non-negative integer, got {steps!r}")
        if too_large := rollout_size_error(z0.shape[0], steps, system.state_shape, z0.itemsize):
            raise ValueError(f"simulate {system.name}: {too_large}")
        if check_overlap:
            system._check_no_overlap(z0, "z0")
        iterator: Any = range(steps)
        if progress:
            from tqdm.auto import tqdm

            iterator = tqdm(iterator, desc=f"simulate {system.name} ({self.model_name})")
        states = [z0]
        z = z0
        with thread_scope(threads, z0.device, steps) as scope:
            for _ in iterator:
                with scope.step():
                    z = self.step(z)
                states.append(z)
        traj = torch.stack(states, dim=1)
        if not bool(torch.isfinite(traj.detach()).all()):
            bad = (~torch.isfinite(traj.detach()).flatten(2).all(-1)).any(-1).nonzero().flatten()
            raise NonFiniteRolloutError(
                f"{self.model_name} rollout of {system.name}: NaN or infinite values in the "
                f"predicted states of {bad.numel()} of {traj.shape[0]} trajectories (the "
                "network diverged)",
                bad.tolist(),
            )
        return traj

    def forward(self, z0: Tensor, steps: int | None = None, **kwargs: Any) -> Tensor:
        """Same as :meth:`simulate`."""
        return self.simulate(z0, steps, **kwargs)


# ----------------------------------------------------------------------------- registry
def MLP_CD_CLNN(config: Any, **options: Any) -> MLPCDCLNN:
    """Registry factory of ``MLP-CD-CLNN``."""
    return MLPCDCLNN(config, **options)


def IN_CP_CLNN(config: Any, **options: Any) -> INCPCLNN:
    """Registry factory of ``IN-CP-CLNN``."""
    return INCPCLNN(config, **options)


def IN_SP_CP(config: Any, **options: Any) -> INSPCP:
    """Registry factory of ``IN-SP-CP``."""
    return INSPCP(config, **options)

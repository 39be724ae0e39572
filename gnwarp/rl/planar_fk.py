"""Forward kinematics of planar chains in few tensor operations, for rewards differentiated inside
an update (SVG(N) on cheetah and walker: ``gnwarp.rl.obs_reward``).

The general ``forward_kinematics`` composes quaternions body by body: some 2500 small torch
operations forward and backward for DMC's cheetah, each a kernel launch on a GPU, even replayed
from a CUDA graph. Where every body rotates about the world's y axis only (every body frame a
rotation about y, every hinge axis +-y, every slide axis in the x-z plane: DMC's cheetah, walker
and hopper), a body's orientation is one pitch angle and its x-z position and velocity one complex
number each: a rotation by ``t`` is a product with ``exp(-i t)`` and ``w x r`` one with ``-i w``,
and the y positions are constants. ``PlanarChain`` computes the bodies of one tree depth together
(one level a few dozen operations), the same states as ``forward_kinematics`` to rounding
(``tests/test_rl_observations.py``, float64, values and gradients). Inside ``torch.compile``
(an update compiled by ``torch_compile``) the complex numbers are pairs of real tensors
(``_Pair``): inductor compiles no complex arithmetic, and so fuses the chain with the reward.

    >>> chain = planar_chain(JointCoordinates(model))      # None where the model is not planar
    >>> body = chain(qpos, qvel)                             # [..., nbody, 13], world first
"""
from __future__ import annotations

import math

import torch

from gnwarp.rl.observations import JointCoordinates

__all__ = ["PlanarChain", "planar_chain", "not_planar"]

_TOL = 1e-12


class _Pair:
    """x + iz as two real tensors (``real``, ``imag``) with the methods of a complex tensor that
    ``PlanarChain`` calls (``add``, ``sub``, ``mul`` by a pair or a real tensor, ``unsqueeze``,
    ``index_select``, ``sum``), in real operations. Methods, not operators: torch.compile (2.13)
    traces a user class's method calls but breaks its graph at its operators."""

    def __init__(self, real: torch.Tensor, imag: torch.Tensor):
        self.real, self.imag = real, imag

    def add(self, o: "_Pair") -> "_Pair":
        return _Pair(self.real + o.real, self.imag + o.imag)

    def sub(self, o: "_Pair") -> "_Pair":
        return _Pair(self.real - o.real, self.imag - o.imag)

    def mul(self, o) -> "_Pair":
        if isinstance(o, _Pair):
            return _Pair(self.real * o.real - self.imag * o.imag, self.real * o.imag + self.imag * o.real)
        return _Pair(self.real * o, self.imag * o)

    def unsqueeze(self, dim: int) -> "_Pair":
        return _Pair(self.real.unsqueeze(dim), self.imag.unsqueeze(dim))

    def index_select(self, dim: int, index: torch.Tensor) -> "_Pair":
        return _Pair(self.real.index_select(dim, index), self.imag.index_select(dim, index))

    def sum(self, dim: int) -> "_Pair":
        return _Pair(self.real.sum(dim), self.imag.sum(dim))


def _complex_ops(c: dict) -> dict:
    """The chain's complex numbers as torch complex tensors (eager: fewest operations)."""
    return dict(rot=lambda t: torch.polar(c["one"].expand_as(t), -t), make=torch.complex, cat=torch.cat,
                const=lambda k: k)


def _pair_ops(c: dict) -> dict:
    """The chain's complex numbers as ``_Pair`` s (inside ``torch.compile``)."""
    return dict(rot=lambda t: _Pair(torch.cos(t), -torch.sin(t)), make=_Pair,
                cat=lambda xs, dim: _Pair(torch.cat([x.real for x in xs], dim), torch.cat([x.imag for x in xs], dim)),
                const=lambda k: _Pair(*k))


def not_planar(coords: JointCoordinates) -> str | None:
    """Why ``coords``' model is not a planar chain about y (None when it is)."""
    for b, _, _, bquat, slides, hinge in coords.bodies:
        if abs(bquat[1]) > _TOL or abs(bquat[3]) > _TOL:
            return f"body {b}'s frame is not a rotation about y"
        for s in slides:
            if abs(s[2][1]) > _TOL:
                return f"body {b} slides along an axis out of the x-z plane"
        if hinge is not None and (abs(hinge[2][0]) > _TOL or abs(hinge[2][2]) > _TOL):
            return f"body {b}'s hinge axis is not +-y"
    return None


def planar_chain(coords: JointCoordinates) -> "PlanarChain | None":
    """``coords``' ``PlanarChain`` (made once, kept on ``coords``), or None where the model is not
    planar about y."""
    chain = getattr(coords, "_planar_chain", False)
    if chain is False:
        chain = PlanarChain(coords) if not_planar(coords) is None else None
        coords._planar_chain = chain
    return chain


class PlanarChain:
    """Body states [..., nbody, 13] of a planar chain (see the module docstring) at joint
    coordinates qpos [..., nq], qvel [..., nv]; differentiable. Raises ValueError where
    ``not_planar(coords)`` gives a reason."""

    def __init__(self, coords: JointCoordinates):
        why = not_planar(coords)
        if why is not None:
            raise ValueError(f"not a planar chain: {why}")
        self.nbody, self.nq, self.nv = coords.nbody, coords.nq, coords.nv
        depth, y = {0: 0}, {0: 0.0}
        spec = {}
        for b, p, bpos, bquat, slides, hinge in coords.bodies:
            depth[b] = depth[p] + 1
            y[b] = y[p] + float(bpos[1])     # rotations about y keep y; slides and hinges add none
            spec[b] = (p, bpos, bquat, slides, hinge)
        self.levels = []   # per depth >= 1: host lists of its bodies' constants
        where = {0: 0}   # body -> its index in its level
        for d in range(1, max(depth.values()) + 1):
            bodies = [b for b in range(1, self.nbody) if depth[b] == d]
            S = max(len(spec[b][3]) for b in bodies)
            lv = dict(bodies=bodies, parent=[where[spec[b][0]] for b in bodies], S=S,
                      beta=[2 * math.atan2(spec[b][2][2], spec[b][2][0]) for b in bodies],
                      bpos=[complex(spec[b][1][0], spec[b][1][2]) for b in bodies],
                      q=[], v=[], axis=[], ref=[], hinge=any(spec[b][4] is not None for b in bodies),
                      hq=[], hv=[], sign=[], href=[], hpos=[])
            for b in bodies:
                slides, hinge = spec[b][3], spec[b][4]
                pad = S - len(slides)
                lv["q"].append([s[0] for s in slides] + [-1] * pad)   # -1: padding (see _constants)
                lv["v"].append([s[1] for s in slides] + [-1] * pad)
                lv["axis"].append([complex(s[2][0], s[2][2]) for s in slides] + [0j] * pad)
                lv["ref"].append([s[3] for s in slides] + [0.0] * pad)
                lv["hq"].append(hinge[0] if hinge else -1)
                lv["hv"].append(hinge[1] if hinge else -1)
                lv["sign"].append(math.copysign(1.0, hinge[2][1]) if hinge else 0.0)
                lv["href"].append(hinge[3] if hinge else 0.0)
                lv["hpos"].append(complex(hinge[4][0], hinge[4][2]) if hinge else 0j)
            where.update((b, i) for i, b in enumerate(bodies))
            self.levels.append(lv)
        order = [0] + [b for lv in self.levels for b in lv["bodies"]]
        self._perm = [order.index(b) for b in range(self.nbody)]   # level order -> body order
        self._y = [y[b] for b in range(self.nbody)]
        self._cache: dict = {}

    def _constants(self, like: torch.Tensor) -> dict:
        key = (like.device, like.dtype)
        c = self._cache.get(key)
        if c is None:
            cd = torch.complex128 if like.dtype == torch.float64 else torch.complex64
            real = lambda v: torch.tensor(v, dtype=like.dtype, device=like.device)   # noqa: E731
            index = lambda v: torch.tensor(v, dtype=torch.long, device=like.device)  # noqa: E731
            cplx = lambda v: torch.tensor(v, dtype=cd, device=like.device)           # noqa: E731
            # a pair constant as (real, imag) tensors: its _Pair is made where it is used, inside
            # the traced function (torch.compile traces the arithmetic of pairs made there)
            pair = lambda v: (real([z.real for z in v]), real([z.imag for z in v]))   # noqa: E731
            c = dict(levels=[], perm=index(self._perm), y=real(self._y), one=real(1.0), mi=cplx(-1j),
                     pairs=dict(mi=(real(0.0), real(-1.0)), levels=[]))
            # a padded slot reads column nq / nv: a zero appended to the coordinates (so that a
            # non-finite coordinate stays in its own body, and no gradient flows to another's)
            pad = lambda rows, n: [[n if k < 0 else k for k in r] for r in rows]   # noqa: E731
            for lv in self.levels:
                c["levels"].append(dict(
                    parent=index(lv["parent"]), beta=real(lv["beta"]), bpos=cplx(lv["bpos"]),
                    q=index(sum(pad(lv["q"], self.nq), [])), v=index(sum(pad(lv["v"], self.nv), [])),
                    axis=cplx(lv["axis"]), ref=real(lv["ref"]),
                    hq=index(pad([lv["hq"]], self.nq)[0]), hv=index(pad([lv["hv"]], self.nv)[0]),
                    sign=real(lv["sign"]), href=real(lv["href"]), hpos=cplx(lv["hpos"])))
                c["pairs"]["levels"].append(dict(c["levels"][-1], bpos=pair(lv["bpos"]),
                                                 axis=(real([[z.real for z in r] for r in lv["axis"]]),
                                                       real([[z.imag for z in r] for r in lv["axis"]])),
                                                 hpos=pair(lv["hpos"])))
            self._cache[key] = c
        return c

    def __call__(self, qpos: torch.Tensor, qvel: torch.Tensor, pairs: bool | None = None) -> torch.Tensor:
        """``pairs``: the complex numbers as pairs of real tensors (None: inside ``torch.compile``
        only; eager, torch's complex tensors take fewer operations)."""
        if qpos.shape[-1] != self.nq or qvel.shape[-1] != self.nv or qpos.shape[:-1] != qvel.shape[:-1]:
            raise ValueError(f"qpos [..., {self.nq}] and qvel [..., {self.nv}] with the same leading shape "
                             f"expected, got {tuple(qpos.shape)} and {tuple(qvel.shape)}")
        c = self._constants(qpos)
        if pairs is None:
            pairs = torch.compiler.is_compiling()
        ops = _pair_ops(c) if pairs else _complex_ops(c)
        k = ops["const"]   # a constant complex number (a pair: made here, from its two tensors)
        mi, levels = (k(c["pairs"]["mi"]), c["pairs"]["levels"]) if pairs else (c["mi"], c["levels"])
        lead = qpos.shape[:-1]
        rot = ops["rot"]   # x + iz rotated by t about y: a product with exp(-i t)
        zero = qpos.new_zeros(*lead, 1)
        qpos, qvel = torch.cat([qpos, zero], -1), torch.cat([qvel, zero], -1)   # column nq / nv: padding
        th, w = [zero], [zero]
        x = [ops["make"](zero, zero)]
        v = [x[0]]
        for h, lv in zip(self.levels, levels):   # host description, device constants
            P = lv["parent"]
            tp, wp = th[-1].index_select(-1, P), w[-1].index_select(-1, P)
            xp, vp = x[-1].index_select(-1, P), v[-1].index_select(-1, P)
            # complex arithmetic as method calls, a complex number on the left: the same code runs
            # on torch's complex tensors (eager) and on _Pairs (inside torch.compile)
            jw = mi.mul(wp)                                      # w x . as a product: -i w
            xb, vb = xp.add(rot(tp).mul(k(lv["bpos"]))), vp
            t0 = tp + lv["beta"]
            e0 = rot(t0)
            G, S = len(h["bodies"]), h["S"]
            if S:
                ax = e0.unsqueeze(-1).mul(k(lv["axis"]))
                xb = xb.add(ax.mul(qpos.index_select(-1, lv["q"]).view(*lead, G, S) - lv["ref"]).sum(-1))
                vb = vb.add(ax.mul(qvel.index_select(-1, lv["v"]).view(*lead, G, S)).sum(-1))
            vb = vb.add(jw.mul(xb.sub(xp)))                      # the parent's rotation carries the point
            if h["hinge"]:
                tb = t0 + lv["sign"] * (qpos.index_select(-1, lv["hq"]) - lv["href"])
                wb = wp + lv["sign"] * qvel.index_select(-1, lv["hv"])
                hpos = k(lv["hpos"])
                a0, a = e0.mul(hpos), rot(tb).mul(hpos)
                # about the anchor (xb + a0): x = anchor - a, v = v_anchor + w x (x - anchor)
                xb = xb.add(a0).sub(a)
                vb = vb.add(jw.mul(a0)).sub(mi.mul(wb).mul(a))
            else:
                tb, wb = t0, wp
            th.append(tb)
            w.append(wb)
            x.append(xb)
            v.append(vb)
        P = c["perm"]
        th, w = torch.cat(th, -1).index_select(-1, P), torch.cat(w, -1).index_select(-1, P)
        x, v = ops["cat"](x, -1).index_select(-1, P), ops["cat"](v, -1).index_select(-1, P)
        z = torch.zeros_like(th)
        half = th / 2
        return torch.stack([x.real, c["y"].expand_as(th), x.imag, torch.cos(half), z, torch.sin(half), z,
                            v.real, z, v.imag, z, w, z], -1)

"""The dictionary: candidate terms beyond the effect library, each linear in its coefficients.

A term is an effect the one forward model can add and the engine can fit:

- a **joint term** adds ``Δqⱼ = φ(q, s, τ) · c`` to one joint's angle, with `q` the logged
  joint angles [rad], `s` the sign of each joint's velocity (0 while it stands still,
  `motion_sign`) and `τ` the gravity torques [N·m];
- an **LED term** moves every LED observation by ``Φ(y, n, θ) · c`` [m] in the camera
  frame, with `y` the LED's position [m], `n` its emission axis and `θ` its emission
  angle [rad].

Terms are linear in their coefficients ``c`` (a phase is a sine and a cosine
coefficient), so their Jacobian columns are closed forms and a whole dictionary is
screened with one pass of the normal equations. The default dictionary
(`default_terms`) has, per joint, harmonics of the joint angle (1 to 4 cycles per
revolution; harmonics of the motor-side angle need a gear ratio, which the built-in
robots do not carry), an error of the sign of the joint velocity and one of the signed square of
the gravity torque; per tracker, LED biases along the emission axis and along the line
of sight, and a scale per camera axis. Users add their own with `register_effect`.

A term may carry a zero-mean Gaussian prior on its coefficients (`Term.precision`): the
fits then add ``cᵀΛc`` to their cost. Each joint also has an angle error map,
``joint{j}_map`` (`robtraj.model._joint_map`: a periodic piecewise-linear error with a
coefficient per knot, `N_KNOTS` per revolution, under a smoothness prior). The maps are
known wherever terms are (`Effects.terms`, `fit(estimate=...)`, `--effect`, CALIB.json,
the pose-level fit) but are not among the discovery search's default candidates
(`dictionary`): its score test takes every candidate's columns in one pass, and a
few hundred coefficients per joint would make that pass and its compilation many
times slower.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import jax.numpy as jnp
import numpy as np

from .._errors import UserError
from . import _constructed, _joint_map

#: joints the default dictionary has terms for (a robot uses those it has)
MAX_JOINTS = 9
#: harmonics of each joint angle in the default dictionary [cycles per revolution]
HARMONICS = (1, 2, 3, 4)
#: emission angle [rad] the LED terms' angle functions are normalised at (as
#: `led_angle_bias`): ``u(θ) = (1 − cos θ)/(1 − cos 60°)``
_U_REF = 1.0 - math.cos(math.radians(60.0))


@dataclasses.dataclass(frozen=True)
class Term:
    """One dictionary term (see the module docstring).

    - `name`: the effect name (``joint1_harmonic2``); `components`: names of its
      coefficients (``("sin", "cos")``), each in `unit`.
    - `kind`: ``"joint"`` (adds to joint `joint`, 0-based) or ``"led"``.
    - `fn`: joint terms ``fn(q, s, τ) -> (k,)`` per frame (rad per unit coefficient);
      LED terms ``fn(y, n, θ) -> (..., 3, k)`` [m per unit coefficient].
    - `variable`: what the term is a function of, in words (``"q1"``, ``"θ"``);
      `function`: the term with coefficients named by its components
      (``"sin·sin(2·q1) + cos·cos(2·q1)"``); `frame_variable`: the variable of the
      discrepancy workflow's localisation the residual is plotted against.
    - `harmonic`: cycles per revolution for a harmonic (reported as amplitude and phase).
    - `motion`: the term acts through `s`; the discrepancy search then also estimates the
      speed below which a joint counts as at rest (a deadband, by profiling
      `fit(motion_threshold=...)`).
    - `precision`: `(k, k)` precision matrix [1/unit²] of a zero-mean Gaussian prior on
      the coefficients, or None (no prior): every fit that estimates the term adds
      ``cᵀΛc`` to its cost (``H += Λ``, ``b −= Λc``), and its covariance is the
      posterior one.
    - `knots`: the knot count of a joint angle error map (`_joint_map`), 0 otherwise.
    - `searched`: among the discovery search's default candidates (`dictionary`).
    - `factors`: a constructed term's factors (`robtraj.model._constructed.Factor`),
      empty for any other term.
    """

    name: str
    kind: str
    components: tuple[str, ...]
    unit: str
    fn: Callable
    variable: str
    function: str
    frame_variable: str
    joint: int = -1
    harmonic: int = 0
    motion: bool = False
    precision: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)
    knots: int = 0
    searched: bool = True
    factors: tuple = ()

    @property
    def size(self) -> int:
        return len(self.components)


def _harmonic(j: int, h: int) -> Term:
    def fn(q, s, tau):
        return jnp.stack([jnp.sin(h * q[j]), jnp.cos(h * q[j])])

    v = f"q{j + 1}"
    return Term(
        name=f"joint{j + 1}_harmonic{h}",
        kind="joint",
        components=("sin", "cos"),
        unit="rad",
        fn=fn,
        variable=v,
        function=f"sin·sin({h}·{v}) + cos·cos({h}·{v})",
        frame_variable=f"joint {j + 1}",
        joint=j,
        harmonic=h,
    )


def _velocity_sign(j: int) -> Term:
    return Term(
        name=f"joint{j + 1}_velocity_sign",
        kind="joint",
        components=("value",),
        unit="rad",
        fn=lambda q, s, tau: s[j : j + 1],
        variable=f"sign(q̇{j + 1})",
        function=f"value·sign(q̇{j + 1}) (0 at rest)",
        frame_variable=f"joint {j + 1} velocity",
        joint=j,
        motion=True,
    )


def _torque_squared(j: int) -> Term:
    return Term(
        name=f"joint{j + 1}_torque_squared",
        kind="joint",
        components=("value",),
        unit="rad/(N·m)²",
        fn=lambda q, s, tau: (tau[j] * jnp.abs(tau[j]))[None],
        variable=f"τ{j + 1}",
        function=f"value·τ{j + 1}·|τ{j + 1}|",
        frame_variable=f"joint {j + 1}",
        joint=j,
    )


def _map(j: int) -> Term:
    n = _joint_map.N_KNOTS
    v = f"q{j + 1}"
    return Term(
        name=f"joint{j + 1}_map",
        kind="joint",
        components=tuple(f"k{k:03d}" for k in range(n)),
        unit="rad",
        fn=lambda q, s, tau: _joint_map.features(q[j], n),
        variable=v,
        function=f"Σₖ cₖ·φₖ({v}): periodic hat functions on {n} knots per revolution",
        frame_variable=f"joint {j + 1}",
        joint=j,
        precision=_joint_map.precision(n),
        knots=n,
        searched=False,
    )


def _u(theta):
    return (1.0 - jnp.cos(theta)) / _U_REF


def _sight(y):
    return y / jnp.linalg.norm(y, axis=-1, keepdims=True)


def _led_terms() -> list[Term]:
    return [
        Term(
            name="led_axis_bias",
            kind="led",
            components=("value",),
            unit="m",
            fn=lambda y, n, th: (n * (_u(th) ** 2)[..., None])[..., None],
            variable="θ",
            function="value·u(θ)² along the emission axis, u = (1 − cos θ)/(1 − cos 60°)",
            frame_variable="emission angle",
        ),
        Term(
            name="led_sight_bias",
            kind="led",
            components=("constant", "angle"),
            unit="m",
            fn=lambda y, n, th: jnp.stack([_sight(y), _sight(y) * _u(th)[..., None]], axis=-1),
            variable="θ",
            function="(constant + angle·u(θ)) along the line of sight, "
            "u = (1 − cos θ)/(1 − cos 60°)",
            frame_variable="emission angle",
        ),
        Term(
            name="tracker_axis_scale",
            kind="led",
            components=("x", "y", "z"),
            unit="1",
            fn=lambda y, n, th: y[..., :, None] * jnp.eye(3, dtype=y.dtype),
            variable="camera x, y, z",
            function="x·y_x, y·y_y, z·y_z (a scale per camera axis)",
            frame_variable="emission angle",
        ),
    ]


def default_terms(n_joints: int = MAX_JOINTS) -> tuple[Term, ...]:
    """The built-in dictionary for a robot of `n_joints` joints (module docstring)."""
    out = []
    for j in range(n_joints):
        out += [_harmonic(j, h) for h in HARMONICS]
        out += [_velocity_sign(j), _torque_squared(j)]
    return (*out, *_led_terms(), *(_map(j) for j in range(n_joints)))


_REGISTRY: dict[str, Term] = {t.name: t for t in default_terms()}
#: names a term may not take: the library's effects (`reserve`, called by `_effects`)
_RESERVED: set[str] = set()
_USER: list[str] = []


def register_effect(
    name: str,
    fn: Callable,
    components: Sequence[str],
    *,
    kind: str = "joint",
    joint: int | None = None,
    unit: str = "rad",
    variable: str = "",
    function: str = "",
    frame_variable: str | None = None,
    motion: bool = False,
    precision: np.ndarray | None = None,
) -> Term:
    """Add a term of the user's to the dictionary (the discrepancy search then tries it).

    `fn` is linear in the coefficients named by `components`: for ``kind="joint"`` the
    term adds ``fn(q, s, τ) @ c`` [rad] to joint `joint` (1-based), with `q` the logged
    joint angles [rad], `s` the signs of the joint velocities (0 at rest) and `τ` the
    gravity torques [N·m], each `(joints,)`, returning `(k,)`; for ``kind="led"`` it
    moves each LED observation by ``fn(y, n, θ) @ c`` [m] (camera frame), with `y`
    `(..., 3)` the LED position, `n` `(..., 3)` its emission axis, `θ` `(...)` its
    emission angle, returning `(..., 3, k)`. `fn` must be a JAX function (it is
    differentiated and compiled). `motion`: a joint term that acts through `s` (the
    discrepancy search then also estimates the speed below which a joint counts as at
    rest). `precision`: `(k, k)` precision matrix [1/unit²] of a zero-mean Gaussian
    prior on the coefficients (`Term.precision`), None for none. Returns the `Term`; a
    name already taken raises `UserError`.
    """
    if not name.isidentifier():
        raise UserError(f"effect name {name!r} must be an identifier")
    if name in _RESERVED or name in _REGISTRY:
        raise UserError(f"effect {name!r} exists already")
    if kind not in ("joint", "led"):
        raise UserError(f"kind must be 'joint' or 'led', got {kind!r}")
    if kind == "joint" and (joint is None or joint < 1):
        raise UserError("a joint term needs joint=N (1-based)")
    if motion and kind != "joint":
        raise UserError("only a joint term acts through the velocity signs (motion=True)")
    comps = tuple(components)
    if not comps:
        raise UserError("a term needs at least one coefficient")
    if precision is not None:
        precision = np.asarray(precision, float)
        if precision.shape != (len(comps), len(comps)) or not np.allclose(precision, precision.T):
            raise UserError(
                f"precision must be a symmetric {len(comps)}×{len(comps)} matrix, "
                f"got shape {precision.shape}"
            )
    j = -1 if kind == "led" else int(joint) - 1
    term = Term(
        name=name,
        kind=kind,
        components=comps,
        unit=unit,
        fn=fn,
        variable=variable or (f"q{j + 1}" if kind == "joint" else "θ"),
        function=function or f"{name}({', '.join(comps)})",
        frame_variable=frame_variable
        or (f"joint {j + 1}" if kind == "joint" else "emission angle"),
        joint=j,
        motion=bool(motion),
        precision=precision,
    )
    _REGISTRY[name] = term
    _USER.append(name)
    return term


def reserve(names) -> None:
    """Keep `names` (the library's effect fields) from being registered as terms."""
    _RESERVED.update(names)


def unregister_effect(name: str) -> None:
    """Remove a term added by `register_effect`."""
    if name not in _USER:
        raise UserError(f"{name!r} is not a registered term")
    _USER.remove(name)
    del _REGISTRY[name]


def term(name: str) -> Term | None:
    """The dictionary term called `name` (None for a library effect or an unknown name);
    a constructed term (`robtraj.model._constructed`) is built from its name the first
    time it is asked for."""
    found = _REGISTRY.get(name)
    if found is None and name not in _RESERVED:
        found = _constructed_term(name)
        if found is not None:
            _REGISTRY[name] = found
    return found


def _constructed_term(name: str) -> Term | None:
    """The constructed term called `name`; None when `name` is not one."""
    parsed = _constructed.parse(name)
    if parsed is None or parsed[0] >= MAX_JOINTS:
        return None
    joint, factors = parsed
    words = _constructed.function_words(factors)
    return Term(
        name=name,
        kind="joint",
        components=_constructed.components(factors),
        unit=_constructed.unit(factors),
        fn=lambda q, s, tau: _constructed.features(factors, q, tau),
        variable=", ".join(
            dict.fromkeys(f"{'q' if f.signal == 'q' else 'τ'}{f.joint + 1}" for f in factors)
        ),
        function=" + ".join(f"{c}·{w}" for c, w in zip(_constructed.components(factors), words)),
        frame_variable=f"joint {factors[0].joint + 1}",
        joint=joint,
        searched=False,
        factors=factors,
    )


def dictionary(n_joints: int) -> tuple[str, ...]:
    """Names of the dictionary's terms for a robot of `n_joints` joints that the discovery
    search tries by default: the built-in ones and those registered, in that order (not
    the joint angle error maps, `Term.searched`)."""
    return tuple(t.name for t in _REGISTRY.values() if t.joint < n_joints and t.searched)


def joint_maps(n_joints: int) -> tuple[str, ...]:
    """Names of the joint angle error maps (``joint{j}_map``) of a robot of `n_joints`
    joints."""
    return tuple(t.name for t in _REGISTRY.values() if t.knots and t.joint < n_joints)


def term_names() -> tuple[str, ...]:
    """Every term name the dictionary knows (any robot)."""
    return tuple(_REGISTRY)


def _joint_terms(names: Sequence[str]) -> list[Term]:
    return [t for t in map(term, names) if t is not None and t.kind == "joint"]


def joint_term_features(
    names: Sequence[str], q: jnp.ndarray, s: jnp.ndarray, tau: jnp.ndarray
) -> jnp.ndarray:
    """The features ``fn(q, s, τ)`` of the joint terms among `names` for one frame,
    concatenated `(k,)` [rad per unit coefficient]: one array for all terms, so that the
    compiled program does not grow by a product per term (`joint_term_joints` says which
    joint each entry acts on)."""
    ts = _joint_terms(names)
    if not ts:
        return jnp.zeros(0, q.dtype)
    return jnp.concatenate([t.fn(q, s, tau) for t in ts])


def joint_term_joints(names: Sequence[str]) -> np.ndarray:
    """The joint (0-based) each entry of `joint_term_features(names, ...)` acts on."""
    return np.array([t.joint for t in _joint_terms(names) for _ in range(t.size)], int)


def joint_term_error(terms: dict, q: jnp.ndarray, s: jnp.ndarray, tau: jnp.ndarray) -> jnp.ndarray:
    """Sum of the joint terms in `terms` {name: coefficients} for one frame `(joints,)` [rad]
    (a map from the two knots around its joint's angle, not from its every feature)."""
    ts = _joint_terms(list(terms))
    out = jnp.zeros_like(q)
    for t in (t for t in ts if t.knots):
        idx, w = _joint_map.active(q[t.joint], t.knots)
        out = out.at[t.joint].add(jnp.sum(w * jnp.asarray(terms[t.name], q.dtype)[idx]))
    names = [t.name for t in ts if not t.knots]
    if not names:
        return out
    c = jnp.concatenate([jnp.asarray(terms[n], q.dtype) for n in names])
    onehot = np.arange(q.shape[0])[None, :] == joint_term_joints(names)[:, None]
    return out + (joint_term_features(names, q, s, tau) * c) @ jnp.asarray(onehot, q.dtype)


def led_term_offset(terms: dict, y, n, theta):
    """Sum of the LED terms in `terms` for LED positions `y` `(..., 3)` [m]."""
    out = jnp.zeros_like(y)
    for name, c in terms.items():
        t = term(name)
        if t.kind == "led":
            out = out + jnp.einsum("...ik,k->...i", t.fn(y, n, theta), c)
    return out


def has_led_terms(names) -> bool:
    return any(t is not None and t.kind == "led" for t in map(term, names))


def amplitude_phase(values: np.ndarray, cov: np.ndarray) -> tuple[float, float, float, float]:
    """``(A, σ_A, φ, σ_φ)`` of ``s·sin x + c·cos x = A·sin(x + φ)`` from ``[s, c]`` and
    their 2×2 covariance (first-order propagation)."""
    s, c = float(values[0]), float(values[1])
    a = math.hypot(s, c)
    phi = math.atan2(c, s)
    if a == 0.0:
        return 0.0, float(np.sqrt(np.trace(cov) / 2)), 0.0, math.pi
    ja = np.array([s, c]) / a
    jp = np.array([-c, s]) / a**2
    return a, float(np.sqrt(max(ja @ cov @ ja, 0.0))), phi, float(np.sqrt(max(jp @ cov @ jp, 0.0)))


def _fmt(value: float, sigma: float, unit: str) -> str:
    """``value ± sigma unit`` in mrad for rad and µm for m: σ to two significant digits
    and the value to the same decimal place (``0.600000 ± 0.000096 mrad``)."""
    scale, unit = {"rad": (1e3, "mrad"), "m": (1e6, "µm")}.get(unit, (1.0, unit))
    value, sigma = _rounded(value * scale, sigma * scale)
    return f"{value} ± {sigma} {unit}"


def _rounded(value: float, sigma: float) -> tuple[str, str]:
    """`sigma` to two significant digits and `value` to the same decimal place."""
    if not (math.isfinite(sigma) and sigma > 0):
        return f"{value:.3g}", f"{sigma:.2g}"
    places = max(0, 1 - math.floor(math.log10(sigma)))
    return f"{value:.{places}f}", f"{sigma:.{places}f}"


def _constructed_words(t: Term, values: np.ndarray, sigma: np.ndarray) -> str:
    """A constructed term in words: its products of basis functions, those more than 2σ
    from zero, the largest first (``joint 2 angle error −0.6000 ± 0.0040 mrad·cos(3·q3)·sin(q4)``;
    per unit of a signal for a linear factor: ``0.310 ± 0.010 mrad per rad of q2``)."""
    words = _constructed.function_words(t.factors)
    per = [f.unit for f in t.factors if f.unit]
    order = np.argsort(-np.abs(values) / np.where(sigma > 0, sigma, np.inf))
    parts = []
    for k in order:
        if abs(values[k]) <= 2 * sigma[k] and parts:
            continue
        size = _fmt(values[k], sigma[k], "rad")
        if per:
            size += f" per {'·'.join(per)} of {words[k]}"
        else:
            size += f"·{words[k]}"
        parts.append(size)
    rest = len(values) - len(parts)
    tail = f" ({rest} more within 2σ of zero)" if rest else ""
    return f"joint {t.joint + 1} angle error " + " + ".join(parts) + tail


def describe(t: Term, values: np.ndarray, cov: np.ndarray) -> str:
    """The term with its fitted coefficients in words, e.g.
    ``joint 1 angle error 0.25 ± 0.01 mrad · sin(2·q1 + 1.00 rad)``."""
    values = np.asarray(values, float)
    cov = np.asarray(cov, float)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    if t.knots:
        return _joint_map.words(t.joint + 1, values, None)
    if t.factors:
        return _constructed_words(t, values, sig)
    if t.harmonic:
        a, sa, phi, sp = amplitude_phase(values, cov)
        phase, phase_sigma = _rounded(abs(phi), sp)
        return (
            f"joint {t.joint + 1} angle error {_fmt(a, sa, t.unit)} · "
            f"sin({t.harmonic}·{t.variable} {'+' if phi >= 0 else '−'} {phase} rad)"
            f" (phase σ {phase_sigma} rad)"
        )
    parts = ", ".join(f"{c} {_fmt(v, s, t.unit)}" for c, v, s in zip(t.components, values, sig))
    what = f"joint {t.joint + 1} angle error" if t.kind == "joint" else t.name.replace("_", " ")
    return f"{what}: {parts}; {t.function}"

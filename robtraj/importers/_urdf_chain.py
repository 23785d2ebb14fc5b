"""A URDF's serial chain of revolute joints as an equivalent standard-DH table.

The URDF is parsed with `yourdfpy` (meshes are not loaded). The chain runs from the
base link (default: the root link) to the flange link (``tool0``, else ``flange``, else
the last link of the chain); fixed joints on it are folded into the transforms. Each
revolute (or continuous) joint gives a line in the base frame at q = 0: a point and the
direction of its axis, with the URDF's positive sense. `dh_from_axes` turns these lines
into DH frames (DH z_{i-1} is joint i's line) by the common-normal construction; the
flange transform is what remains, so DH forward kinematics equals the URDF's for every
q (both are the product of the same screw motions applied to the same zero pose).
The DH joint angles are the URDF's, so a revolute joint's ``<limit lower upper>`` is its
range as it stands (a bound the file leaves out: none on that side); a continuous joint
has none.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from pathlib import Path

import numpy as np

from .._errors import UserError
from ..model import dh_link_matrix

_DEFAULT_MASS = 5.0  # kg, a link without <inertial><mass>
_BASE_TOL = 1e-9  # first joint axis farther than this from the base z axis: refused
_PARALLEL_TOL = 1e-9  # |z_i-1 × z_i| below this: parallel axes
_TIE_TOL = 1e-12  # |x_i-1 · x_i| below this: θ = ±π/2 either way
_CHECK_TOL = 1e-7  # DH axes farther than this from the URDF's (m, rad): refused


@dataclasses.dataclass(frozen=True)
class UrdfChain:
    """A URDF's chain: `dh` `(J, 4)` [m, m, rad, rad], `last_from_flange` `(4, 4)` (the
    flange in the last DH frame), `link_mass` `(J,)` [kg], the chain's `joint_names`;
    `joint_limits` `(J, 2)` [rad] ``[lower, upper]`` per joint (±inf: none on that
    side), None where no joint has a limit."""

    name: str
    joint_names: tuple[str, ...]
    dh: np.ndarray
    last_from_flange: np.ndarray
    link_mass: np.ndarray
    payload_mass: float | None = None
    joint_limits: np.ndarray | None = None


def read_urdf_chain(
    path: Path, *, flange_link: str | None = None, base_link: str | None = None
) -> UrdfChain:
    """The DH equivalent of the URDF at `path` (see the module docstring); `UserError`
    (one line) for malformed XML, no serial chain of revolute joints to the flange,
    prismatic, floating, planar or mimic joints, a first joint axis that is not the
    base z axis, or a joint limit with lower > upper."""
    robot = _load(path)
    tree = _Tree(path, robot)
    flange_link = flange_link or tree.flange_link()
    base_link = base_link or tree.root
    for role, name in (("flange", flange_link), ("base", base_link)):
        if name not in tree.links:
            raise UserError(f"{path}: no link named {name!r} (the {role} link)")
    chain = tree.serial_chain(base_link, flange_link)
    joints = [j for j in chain if j.type != "fixed"]
    base_from_root = _inverse(tree.fixed_pose(base_link))
    points, directions, base_from_flange = _axis_lines(path, chain, base_from_root)
    first = f"{path}: joint {joints[0].name!r}"
    dh, last_from_flange = dh_from_axes(points, directions, base_from_flange, first=first)
    return UrdfChain(
        name=robot.name,
        joint_names=tuple(j.name for j in joints),
        dh=dh,
        last_from_flange=last_from_flange,
        link_mass=np.array([tree.mass(j.child, flange_link) for j in joints], np.float64),
        payload_mass=tree.payload(flange_link),
        joint_limits=_joint_limits(path, joints),
    )


def _joint_limits(path: Path, joints: list) -> np.ndarray | None:
    """`(J, 2)` [rad] ``[lower, upper]`` of the movable `joints` (continuous, or a bound
    left out: ±inf), None where none has a finite bound."""
    rows = []
    for j in joints:
        limit = j.limit if j.type == "revolute" else None
        lower = getattr(limit, "lower", None)
        upper = getattr(limit, "upper", None)
        row = [
            -np.inf if lower is None else float(lower),
            np.inf if upper is None else float(upper),
        ]
        if not row[0] <= row[1]:
            raise UserError(
                f"{path}: joint {j.name!r} has limits lower {row[0]:g} > upper {row[1]:g} [rad]"
            )
        rows.append(row)
    limits = np.array(rows, np.float64)
    return limits if np.isfinite(limits).any() else None


class _Tree:
    """The URDF's links and joints as a tree, checked: unique names, defined links, one
    parent per link, one root."""

    def __init__(self, path: Path, robot) -> None:
        self.path = path
        for kind, items in (("link", robot.links), ("joint", robot.joints)):
            names = [x.name for x in items]
            twice = sorted({n for n in names if names.count(n) > 1})
            if twice:
                raise UserError(f"{path}: {kind} {twice[0]!r} is defined twice")
        self.links = {link.name: link for link in robot.links}
        self.parent_joint, self.children = {}, defaultdict(list)
        for j in robot.joints:
            for end in (j.parent, j.child):
                if end not in self.links:
                    raise UserError(
                        f"{path}: joint {j.name!r} names link {end!r}, which is not defined"
                    )
            if j.child in self.parent_joint:
                raise UserError(f"{path}: link {j.child!r} is the child of two joints")
            self.parent_joint[j.child] = j
            self.children[j.parent].append(j)
        roots = [name for name in self.links if name not in self.parent_joint]
        if len(roots) != 1:
            names = ", ".join(roots)
            raise UserError(f"{path}: {len(roots)} root links ({names}), expected one tree")
        self.root = roots[0]
        self.movable = [j for j in robot.joints if j.type != "fixed"]

    def chain_to(self, link: str) -> list:
        """The joints from the root to `link`."""
        out, seen = [], set()
        while link in self.parent_joint:
            if link in seen:
                raise UserError(f"{self.path}: the joints form a cycle through link {link!r}")
            seen.add(link)
            out.append(self.parent_joint[link])
            link = self.parent_joint[link].parent
        return out[::-1]

    def flange_link(self) -> str:
        """``tool0``, else ``flange``, else the link after the deepest movable joint
        followed down single fixed joints."""
        for name in ("tool0", "flange"):
            if name in self.links:
                return name
        if not self.movable:
            raise UserError(f"{self.path}: no revolute joint (fewer than 1 movable joint)")
        link = max(self.movable, key=lambda j: len(self.chain_to(j.child))).child
        while self.children[link]:
            if len(self.children[link]) > 1:
                names = ", ".join(j.child for j in self.children[link])
                raise UserError(
                    f"{self.path}: cannot tell the flange link, {link!r} branches into "
                    f"{names}; name it (flange_link)"
                )
            link = self.children[link][0].child
        return link

    def fixed_pose(self, link: str) -> np.ndarray:
        """root←`link`, which must not move (`UserError` otherwise)."""
        pose = np.eye(4)
        for j in self.chain_to(link):
            if j.type != "fixed":
                raise UserError(f"{self.path}: base link {link!r} moves with joint {j.name!r}")
            pose = pose @ _origin(j)
        return pose

    def serial_chain(self, base_link: str, flange_link: str) -> list:
        """The joints from the root to the flange, checked: revolute, continuous or fixed,
        no mimic, at least one revolute, and no movable joint elsewhere."""
        chain = self.chain_to(flange_link)
        for j in chain:
            if j.type in ("prismatic", "floating", "planar"):
                raise UserError(f"{self.path}: joint {j.name!r} is {j.type}; only revolute joints")
            if j.type not in ("fixed", "revolute", "continuous"):
                raise UserError(f"{self.path}: joint {j.name!r} has unknown type {j.type!r}")
            if j.mimic is not None:
                raise UserError(
                    f"{self.path}: joint {j.name!r} mimics {j.mimic.joint!r}; not supported"
                )
        tool = self.below(flange_link)
        off = [
            j.name for j in self.movable if all(j is not c for c in chain) and j.child not in tool
        ]
        if off:
            raise UserError(
                f"{self.path}: joints {', '.join(off)} are not on the chain from {base_link!r} "
                f"to {flange_link!r} (several movable chains): give a URDF of the arm alone"
            )
        if all(j.type == "fixed" for j in chain):
            raise UserError(
                f"{self.path}: no revolute joint between {base_link!r} and {flange_link!r}"
            )
        return chain

    def below(self, link: str) -> set[str]:
        """The links beyond `link` (its subtree, `link` excluded): the tool on a flange."""
        out, todo = set(), [j.child for j in self.children[link]]
        while todo:
            name = todo.pop()
            out.add(name)
            todo += [j.child for j in self.children[name]]
        return out

    def _masses(self, links) -> list[float]:
        inertials = (self.links[name].inertial for name in links)
        return [float(i.mass) for i in inertials if i is not None and i.mass is not None]

    def mass(self, link: str, flange_link: str) -> float:
        """Mass [kg] of `link` and the links fixed to it short of the flange link (5 kg
        if none gives a mass)."""
        links, todo = [], [link]
        while todo:
            name = todo.pop()
            links.append(name)
            todo += [
                j.child for j in self.children[name] if j.type == "fixed" and j.child != flange_link
            ]
        masses = self._masses(links)
        return sum(masses) if masses else _DEFAULT_MASS

    def payload(self, flange_link: str) -> float | None:
        """Mass [kg] of the flange link and all beyond it (the tool, a gripper), None if
        none of them gives a mass."""
        masses = self._masses([flange_link, *self.below(flange_link)])
        return sum(masses) if masses else None


def _axis_lines(path: Path, chain: list, base_from_root: np.ndarray):
    """Per movable joint of `chain` at q = 0: a point `(3,)` of its axis and its unit
    direction `(3,)` in the base frame; and base←(chain's last link)."""
    frame = base_from_root
    points, directions = [], []
    for j in chain:
        frame = frame @ _origin(j)  # base←(the joint's child link) at q = 0
        if j.type != "fixed":
            axis = np.asarray(j.axis, np.float64)
            norm = np.linalg.norm(axis)
            if not np.isfinite(norm) or norm < 1e-12:
                raise UserError(f"{path}: joint {j.name!r} has a zero axis")
            points.append(frame[:3, 3])
            directions.append(frame[:3, :3] @ axis / norm)
    return np.array(points), np.array(directions), frame


def _inverse(pose: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3].T
    out[:3, 3] = -pose[:3, :3].T @ pose[:3, 3]
    return out


def _load(path: Path):
    import yourdfpy
    from lxml import etree

    parser = etree.XMLParser(resolve_entities=False, no_network=True)
    try:
        root = etree.parse(str(path), parser).getroot()
    except etree.XMLSyntaxError as e:
        raise UserError(f"{path}: not well-formed XML ({e})") from None
    if root.tag != "robot" or "name" not in root.attrib:
        raise UserError(f"{path}: not a URDF (the root element is not <robot name=...>)")
    for j in root.findall("joint"):
        name = j.get("name")
        ends = [j.find(e) for e in ("parent", "child")]
        if (
            name is None
            or j.get("type") is None
            or any(e is None or "link" not in e.attrib for e in ends)
        ):
            raise UserError(
                f"{path}: joint {name!r} needs a name, a type, a parent and a child link"
            )
    try:
        urdf = yourdfpy.URDF.load(
            str(path),
            build_scene_graph=False,
            build_collision_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except (KeyError, AttributeError, ValueError, TypeError, IndexError) as e:
        raise UserError(f"{path}: not a valid URDF ({type(e).__name__}: {e})") from None
    return urdf.robot


def _origin(joint) -> np.ndarray:
    return np.eye(4) if joint.origin is None else np.asarray(joint.origin, np.float64)


def dh_from_axes(
    points: np.ndarray, directions: np.ndarray, base_from_end: np.ndarray, first: str = "joint 1"
) -> tuple[np.ndarray, np.ndarray]:
    """Standard-DH rows and last←end for revolute joints on the lines through `points`
    `(J, 3)` [m] along unit `directions` `(J, 3)` (base frame, q = 0), whose end frame at
    q = 0 is `base_from_end` `(4, 4)`.

    DH frame 0 is the base, so joint 1's line must be the base z axis (`UserError`
    naming `first` otherwise). Frame i (i < J) has its origin where the common normal of
    lines i and i+1 meets line i+1 and x_i along that normal; of its two senses the one
    nearer x_{i-1} (θ offset in [−π/2, π/2]), at a tie the one away from line i (a ≥ 0).
    Parallel lines: the normal through the previous origin (d = 0); coincident lines:
    x_i = x_{i-1}. The last frame is the last joint's frame turned by q only, moved along
    its axis to the end frame's foot (a = α = θ = 0); the rest is last←end.
    """
    p1, z1 = points[0], directions[0]
    if np.linalg.norm(z1 - [0.0, 0.0, 1.0]) > _BASE_TOL or np.hypot(p1[0], p1[1]) > _BASE_TOL:
        raise UserError(
            f"{first} turns about the line through ({p1[0]:.6g}, {p1[1]:.6g}) m along "
            f"({z1[0]:.6g}, {z1[1]:.6g}, {z1[2]:.6g}), not the base z axis: robtraj's DH base "
            "frame has its z axis along the first joint axis (choose such a base link)"
        )
    o, x, z = np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    rows = []
    for i in range(points.shape[0]):
        if i + 1 < points.shape[0]:
            w = directions[i + 1]
            d, a, x_new = _common_normal(o, x, z, points[i + 1], w)
        else:
            w, x_new, a = z, x, 0.0
            d = float((base_from_end[:3, 3] - o) @ z)
        alpha = np.arctan2(np.cross(z, w) @ x_new, z @ w)
        theta = np.arctan2(np.cross(x, x_new) @ z, x @ x_new)
        rows.append([d, a, alpha, theta])
        o, x, z = o + d * z + a * x_new, x_new, w
    dh = np.array(rows, np.float64)
    frames = [np.eye(4)]
    for row in dh:
        frames.append(frames[-1] @ dh_link_matrix(row))
    # the construction's promise: DH z_{i-1} is joint i's line with its sense
    z_axes = np.array([f[:3, 2] for f in frames[:-1]])
    off_line = np.cross(points - np.array([f[:3, 3] for f in frames[:-1]]), z_axes)
    err = max(np.abs(z_axes - directions).max(), np.abs(off_line).max())
    if err > _CHECK_TOL:
        raise UserError(f"{first}: the joint axes have no accurate DH form (error {err:.3g})")
    return dh, np.linalg.solve(frames[-1], base_from_end)


def _common_normal(o, x, z, p, w) -> tuple[float, float, np.ndarray]:
    """d, a and x_i of the DH step from frame (o, x, z) to the line through p along w."""
    r = p - o
    c = np.cross(z, w)
    s = np.linalg.norm(c)
    if s > _PARALLEL_TOL:
        n = c / s
        t = float(np.cross(r, w) @ c) / s**2  # foot of the normal on line i: o + t z
    else:  # parallel: the normal through o
        t = 0.0
        v = r - (r @ z) * z
        dist = np.linalg.norm(v)
        if dist <= _PARALLEL_TOL:  # coincident
            return 0.0, float(v @ x), x
        n = v / dist
    sense = n @ x
    if abs(sense) < _TIE_TOL:
        sense = r @ n if abs(r @ n) > _PARALLEL_TOL else 1.0
    x_new = n if sense > 0 else -n
    return t, float(r @ x_new), x_new

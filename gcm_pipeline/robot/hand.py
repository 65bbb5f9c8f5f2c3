"""The hand of a robot model: the links that may touch the object at a grasp.

The *hand* (MoveIt's end-effector group) is what ``environment.contact_tolerance``
lets press into the object at the grasp, and what a TCP-only tool's warning looks
for. By default (:func:`hand_links`) it is every link that moves rigidly with the
grasp frame beyond the arm's last free joint, except the links on the way from
that joint to the grasp frame's link: the link carrying the grasp frame and all
below it (the Panda's ``panda_hand`` and fingers; a tool's flange), and the links
beside that way (a Kinova Jaco2's fingers, siblings of its
``j2s6s200_end_effector``; the fingers of TIAGo's hand beside its
``hand_grasping_frame``) that have a mass (a massless link is a marker frame, as
UR's ``ee_link``, a 1 cm box beside ``tool0``). The wrist link the last free joint
moves stays the arm's unless the grasp frame hangs on it (Jaco2's
``j2s6s200_link_6`` under a tool on ``j2s6s200_end_effector``). A tool with
collision shapes is the hand itself: then only the flange's link and what lies
below it join the tool's shapes.

A spec's ``hand_links`` replaces the default with MoveIt's explicit list
(:func:`checked_hand_links`); a link a free joint moves relative to the grasp
frame is arm, not hand, and refused. A spec's ``drop_collision`` names links
whose collision geometry is not loaded (:func:`checked_drop_collision`: TIAGo's
``hand_safety_box``, a box around the whole hand that every grasp would hit).
"""

from __future__ import annotations

import difflib
import xml.etree.ElementTree as ET
from collections.abc import Collection, Sequence

import pinocchio as pin

from gcm_pipeline.errors import RobotSpecError, choice_error

__all__ = [
    "checked_drop_collision",
    "checked_hand_links",
    "hand_links",
    "urdf_links",
    "wrist_link",
]


def _frame_body(model: pin.Model, fid: int, free_joints: Collection[str]) -> int:
    """The nearest BODY frame above ``fid`` (not ``fid`` itself); ``fid`` at the root.

    Also ``fid`` itself when it is a link that a free joint moves relative to that BODY
    frame (a grasp frame on a wrist link: the link before the joint is the arm's).
    """
    own = model.frames[fid].type == pin.FrameType.BODY
    k = int(model.frames[fid].parentFrame)
    while k != fid and k > 0:
        frame = model.frames[k]
        if frame.type == pin.FrameType.BODY:
            return k
        if own and frame.type == pin.FrameType.JOINT and frame.name in free_joints:
            return fid
        k = int(frame.parentFrame)
    return fid


def _ancestors(model: pin.Model, fid: int) -> list[int]:
    """``fid`` and its ancestors in the frame tree, up to (without) the universe."""
    out, seen = [], set()
    while fid > 0 and fid not in seen:
        seen.add(fid)
        out.append(fid)
        fid = int(model.frames[fid].parentFrame)
    return out


def hand_links(
    full: pin.Model,
    grasp_frame_id: int,
    free_joints: Collection[str],
    beside: bool = True,
    massive: Collection[str] = (),
) -> frozenset[str]:
    """The hand's links by default (see the module docstring).

    Args:
        full: The unreduced model (locked joints still joints).
        grasp_frame_id: The grasp frame's index in ``full``.
        free_joints: The arm's free joints.
        beside: Count the links beside the way from the last free joint to the grasp
            frame's link; without, only that link and all below it (a tool with
            collision shapes is the hand: what else hangs on the wrist, as UR's
            ``ee_link``, is not).
        massive: The links with a mass; a link beside that way joins the hand only
            with one (a massless link is a marker frame, as UR's ``ee_link``).

    Returns:
        Names of the hand's BODY frames, with or without collision geometry.
    """
    frames = full.frames
    root = _frame_body(full, grasp_frame_id, free_joints)
    chain, child = _last_free_joint(full, root, free_joints)
    # the frames from it down to the grasp frame's link (that link is the hand's)
    arm_way = set(chain[1 : chain.index(child) + 1])
    if not beside:
        child = root
    names = set()
    for i, f in enumerate(frames):
        if f.type != pin.FrameType.BODY or i in arm_way:
            continue
        up = _ancestors(full, i)
        if root in up or (child in up and f.name in massive):
            names.add(str(f.name))
    return frozenset(names)


def _last_free_joint(
    full: pin.Model, root: int, free_joints: Collection[str]
) -> tuple[list[int], int]:
    """``root``'s chain of frames (:func:`_ancestors`) and the last free joint's frame on it.

    The joint's frame is the highest frame of the chain that the joint carries (``root``
    when no free joint moves it).
    """
    frames = full.frames
    joint = int(frames[root].parentJoint)
    while joint > 0 and full.names[joint] not in free_joints:
        joint = int(full.parents[joint])
    chain = _ancestors(full, root)
    carried = [f for f in chain if int(frames[f].parentJoint) == joint and joint > 0]
    return chain, carried[-1] if carried else root


def wrist_link(full: pin.Model, grasp_frame_id: int, free_joints: Collection[str]) -> str:
    """The link the arm's last free joint moves, on the way to the grasp frame.

    A hand the model has is more than this link: a TCP-only tool on a bare wrist
    (Bravo 7 without its jaws) still has no hand to collision-check.
    """
    root = _frame_body(full, grasp_frame_id, free_joints)
    chain, joint_frame = _last_free_joint(full, root, free_joints)
    below = chain[: chain.index(joint_frame)]
    body = next((f for f in reversed(below) if full.frames[f].type == pin.FrameType.BODY), root)
    return str(full.frames[body].name)


def urdf_links(xml: str) -> tuple[list[str], set[str], set[str]]:
    """The URDF's links in file order, those with collision geometry and those with a mass."""
    links = list(ET.fromstring(xml).iter("link"))

    def mass(link: ET.Element) -> float:
        try:
            return float(link.find("inertial/mass").get("value", "0"))  # type: ignore[union-attr]
        except (AttributeError, ValueError):
            return 0.0

    return (
        [str(link.get("name")) for link in links],
        {str(link.get("name")) for link in links if link.find("collision") is not None},
        {str(link.get("name")) for link in links if mass(link) > 0},
    )


def _unknown_link(key: str, name: str, links: Sequence[str], where: str) -> RobotSpecError:
    return choice_error(RobotSpecError, "link", name, links, key=key, prefix=f"{where}: {key}: ")


def checked_hand_links(
    given: Sequence[str], model: pin.Model, grasp_frame_id: int, links: Sequence[str], where: str
) -> frozenset[str]:
    """A spec's ``hand_links``, each a URDF link that moves rigidly with the grasp frame.

    Args:
        given: The spec's list.
        model: The reduced model (free joints only).
        grasp_frame_id: The grasp frame's index in ``model``.
        links: The URDF's links.
        where: ``robot 'name'``, for messages.

    Raises:
        RobotSpecError: An unknown link (the close names listed), or one a free joint
            moves relative to the grasp frame (an arm link, not the hand's).
    """
    grasp_joint = int(model.frames[grasp_frame_id].parentJoint)
    for name in given:
        if name not in links:
            raise _unknown_link("hand_links", name, links, where)
        fid = int(model.getFrameId(name, pin.FrameType.BODY))
        joint = int(model.frames[fid].parentJoint)
        if joint != grasp_joint:
            moved = model.names[max(joint, grasp_joint)]
            raise RobotSpecError(
                f"{where}: hand_links: link {name!r} does not move with the grasp frame "
                f"{model.frames[grasp_frame_id].name!r} (the free joint {moved!r} moves one "
                "relative to the other): it is an arm link; list only links fixed to the hand "
                "(or lock the joints between them)",
                key="hand_links",
                value=name,
            )
    return frozenset(given)


def checked_drop_collision(
    given: Sequence[str], links: Sequence[str], with_collision: Collection[str], where: str
) -> frozenset[str]:
    """A spec's ``drop_collision``: URDF links that have collision geometry.

    Raises:
        RobotSpecError: An unknown link, or a link without collision geometry (the
            close names among the links that have some are listed).
    """
    for name in given:
        if name not in links:
            raise _unknown_link("drop_collision", name, links, where)
        if name not in with_collision:
            close = difflib.get_close_matches(name, sorted(with_collision), n=5, cutoff=0.4)
            raise RobotSpecError(
                f"{where}: drop_collision: link {name!r} has no collision geometry to drop; "
                f"links with collision geometry close to it: {', '.join(close) or '(none)'}",
                key="drop_collision",
                value=name,
            )
    return frozenset(given)

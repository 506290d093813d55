"""The Location Publisher core: poses of a module's links, from its own joint angles.

Each pose is published on its own topic in the module's namespace (``pose/tip_link``), so a
ground station that wants one link of one module subscribes to that one resource. Poses are
in the module's root frame (``limb1_base_link``): a module knows only its own joints, and
where its root sits in the assembly depends on the modules it is bolted to (whose
publishers carry their own part). For ROS tools the same placements go on the module's
``tf`` topic as ``tf2_msgs/TFMessage``, plus, from the root-link publisher, the static edge
the module hangs from (another module's connector, or ``world``) so the per-module trees join.

Pure: no clock, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from components.executor.core import Core
from components.kinematics_manager.model import KinematicModel
from components.kinematics_manager.poses import apart, pose_stamped, tf_message, transform_stamped


@dataclass(frozen=True)
class LocationConfig:
    """Rate limits of one location publisher.

    Attributes:
        position_threshold: Link movement (m) that publishes at once.
        angle_threshold: Link rotation (rad) that publishes at once.
        min_period: Shortest time between two publications of a link (rate limit); a
            change held back goes out on the next tick.
        keepalive_period: Every pose is republished this often when nothing moves.
    """

    position_threshold: float = 1e-4
    angle_threshold: float = 1e-3
    min_period: float = 0.02
    keepalive_period: float = 1.0

    def __post_init__(self) -> None:
        if not self.keepalive_period > 0:
            raise ValueError(
                f"LocationConfig.keepalive_period must be > 0, not {self.keepalive_period}"
            )
        for name in ("position_threshold", "angle_threshold", "min_period"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"LocationConfig.{name} must be >= 0, not {getattr(self, name)}")


@dataclass(frozen=True)
class StaticEdge:
    """A fixed transform put on ``tf`` as is (``child`` placed in ``parent``)."""

    parent: str
    child: str
    placement: pin.SE3


def pose_topic(module: str, link: str) -> str:
    """The relative topic of a link's pose: ``pose/<link without the module's prefix>``."""
    prefix = f"{module}_"
    return "pose/" + (link[len(prefix) :] if link.startswith(prefix) else link)


class _Link:
    __slots__ = ("name", "placement", "published", "published_at", "supports", "topic")

    def __init__(self, name: str, topic: str, supports: np.ndarray) -> None:
        self.name = name
        self.topic = topic
        self.supports = supports
        self.placement: pin.SE3 | None = None
        self.published: pin.SE3 | None = None
        self.published_at: float | None = None


class LocationCore(Core):
    """Forward kinematics of some of a module's links, published per link and on ``tf``.

    Args:
        name: Component name (``limb1/location_tip``).
        module: The module's slot (``limb1``).
        model: The module's model (rooted at its root link).
        links: The links this publisher publishes.
        static_edges: Fixed transforms added to every ``tf`` publication (the mount edge).
        config: Rate limits.
    """

    def __init__(
        self,
        name: str,
        module: str,
        model: KinematicModel,
        links: Sequence[str],
        static_edges: Sequence[StaticEdge] = (),
        config: LocationConfig | None = None,
    ) -> None:
        super().__init__(name)
        self.module = module
        self.model = model
        self.config = config or LocationConfig()
        self.frame = model.root_link
        self.static_edges = tuple(static_edges)
        self.q = np.zeros(model.nq)
        self._seen = np.zeros(model.nq, dtype=bool)
        self.links: list[_Link] = []
        for link in links:
            model.frame_id(link)  # fails early, naming the link, if the model lacks it
            supports = np.array([model.index(j) for j in model.supporting_joints(link)], dtype=int)
            self.links.append(_Link(link, pose_topic(module, link), supports))

    @property
    def topics(self) -> list[str]:
        """The pose topics this publisher writes (relative)."""
        return [link.topic for link in self.links]

    def start(self, now: float) -> None:
        """Publish what is known without any joint (the root link, static edges) at once."""
        self._update()
        self._publish_due(now)

    def on_joint_read(self, message: Any, now: float) -> None:
        """Take the module's new angles; publish the links that moved."""
        if self.model.take_positions(message, self.q, self._seen):
            self._update()
            self._publish_due(now)

    def tick(self, now: float) -> None:
        """Held-back changes and keep-alives."""
        self._publish_due(now)

    def _update(self) -> None:
        known = [link for link in self.links if self._seen[link.supports].all()]
        if not known:
            return
        placements = self.model.placements(self.q, [link.name for link in known])
        for link, placement in zip(known, placements, strict=True):
            link.placement = placement

    def _publish_due(self, now: float) -> None:
        cfg = self.config
        sent = []
        for link in self.links:
            if link.placement is None:
                continue  # some joint it hangs from has not been read yet
            last = link.published_at
            if last is not None and now - last < cfg.min_period:
                continue
            due = last is None or now - last >= cfg.keepalive_period
            if not due and link.published is not None:
                distance, angle = apart(link.placement, link.published)
                due = distance > cfg.position_threshold or angle > cfg.angle_threshold
            if due:
                self.publish(link.topic, pose_stamped(link.placement, self.stamp(now), self.frame))
                link.published = link.placement
                link.published_at = now
                sent.append(link)
        if sent:
            self._publish_tf(sent, now)

    def _publish_tf(self, links: list[_Link], now: float) -> None:
        stamp = self.stamp(now)
        transforms = [
            transform_stamped(link.placement, stamp, self.frame, link.name)
            for link in links
            if link.name != self.frame  # tf2 refuses a frame placed in itself
        ]
        transforms.extend(
            transform_stamped(e.placement, stamp, e.parent, e.child) for e in self.static_edges
        )
        if transforms:
            self.publish("tf", tf_message(transforms))

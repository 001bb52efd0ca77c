"""CDR bytes of the display topics, without ROS: written into a template, not built as messages.

Building ``/formation/markers`` as rclpy messages cost ~20 ms of CPU per frame for 20 agents
(~140 Marker objects, their Points and ColorRGBAs, then rclpy's field-by-field conversion):
60 % of the simulator's CPU in a realtime run at 30 Hz (BENCHMARKS.md). A formation's
scene has the same markers at every instant (namespaces, ids, types, texts, point counts): only
poses, points and colours move. So the message is laid out once as little-endian CDR (the layout
rclpy publishes; formation_msgs_py.codec does the same for the per-step messages) and each frame
writes the moving numbers into it through numpy views: a few array assignments per frame.
tests/ros/test_display_wire.py checks the bytes against rclpy's own serialization.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np

from formation_sim.views.markers import CONTACT_COLOUR, FormationScene, SceneFrame, Shape

_CDR_LE = b"\x00\x01\x00\x00"
_ADD = 0  # visualization_msgs/Marker.ADD


class CdrTemplate:
    """Little-endian CDR bytes written field by field; numbers written later are found by index.

    Alignment counts from the end of the 4-byte encapsulation header, so a float64 sits at an
    absolute offset ≡ 4 (mod 8) and every 4-byte field at a multiple of 4: :meth:`views` indexes
    them as arrays (``u32``, ``f32``: absolute offset / 4; ``f64``: (offset − 4) / 8).
    """

    def __init__(self) -> None:
        self.buf = bytearray(_CDR_LE)
        self.size = 0  # of the message, set by :meth:`views`

    def _align(self, size: int) -> None:
        self.buf += bytes((-(len(self.buf) - 4)) % size)

    def u32(self, value: int) -> int:
        """A uint32 (an int32 ≥ 0, a sequence length); its u32 index."""
        self._align(4)
        index = len(self.buf) // 4
        self.buf += struct.pack("<I", value)
        return index

    def i32(self, value: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", value)

    def boolean(self, value: bool) -> None:
        self.buf += b"\x01" if value else b"\x00"

    def string(self, text: str) -> None:
        raw = text.encode("utf-8") + b"\0"
        self.u32(len(raw))
        self.buf += raw

    def f64(self, values: Sequence[float]) -> int:
        """float64 values (a fixed group, or a sequence's elements); the f64 index of the first."""
        if values:
            self._align(8)
        index = (len(self.buf) - 4) // 8
        self.buf += struct.pack(f"<{len(values)}d", *values)
        return index

    def f32(self, values: Sequence[float]) -> int:
        """float32 values; the f32 index of the first."""
        if values:
            self._align(4)
        index = len(self.buf) // 4
        self.buf += struct.pack(f"<{len(values)}f", *values)
        return index

    def views(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u32, f32, f64) arrays over the bytes: writing them writes the message (:meth:`message`).

        Ends the template: the bytes are padded to whole words for the views (not sent).
        """
        self.size = len(self.buf)
        self.buf += bytes((-len(self.buf)) % 8)
        u32 = np.frombuffer(self.buf, dtype="<u4")
        f32 = np.frombuffer(self.buf, dtype="<f4")
        f64 = np.frombuffer(self.buf, dtype="<f8", offset=4, count=(len(self.buf) - 4) // 8)
        return u32, f32, f64

    def message(self) -> bytes:
        """The message as it stands (a copy: the next frame may be written meanwhile)."""
        return bytes(memoryview(self.buf)[: self.size])

    def stamp(self) -> int:
        """A builtin_interfaces/Time (sec, nanosec), zero; the u32 index of sec."""
        index = self.u32(0)
        self.u32(0)
        return index


def _marker(cdr: CdrTemplate, s: Shape, frame_id: str) -> tuple[int, int, int, int]:
    """One visualization_msgs/Marker; u32 index of its stamp, f64 of its pose and points, f32 of its colour."""
    stamp = cdr.stamp()
    cdr.string(frame_id)
    cdr.string(s.ns)
    cdr.i32(s.id)
    cdr.i32(s.type)
    cdr.i32(_ADD)
    pose = cdr.f64([*s.position, *s.orientation])
    cdr.f64(s.scale)
    colour = cdr.f32(s.color)
    cdr.stamp()  # lifetime 0: forever
    cdr.boolean(False)  # frame_locked
    cdr.u32(len(s.points))
    points = cdr.f64([x for pt in s.points for x in pt])
    cdr.u32(len(s.colors))
    cdr.f32([x for c in s.colors for x in c])
    cdr.string("")  # texture_resource
    cdr.stamp()  # texture (sensor_msgs/CompressedImage): header, format, data: empty
    cdr.string("")
    cdr.string("")
    cdr.u32(0)
    cdr.u32(0)  # uv_coordinates
    cdr.string(s.text)
    cdr.string("")  # mesh_resource
    cdr.string("")  # mesh_file: filename, data
    cdr.u32(0)
    cdr.boolean(False)  # mesh_use_embedded_materials
    return stamp, pose, points, colour


def _rows(starts: list[int], width: int) -> np.ndarray:
    """(len(starts), width) indices: ``width`` consecutive values from each start."""
    return np.asarray(starts, dtype=np.intp)[:, None] + np.arange(width)


class MarkerArrayWire:
    """``/formation/markers`` (visualization_msgs/MarkerArray) of a scene as CDR bytes.

    The markers are those of :meth:`FormationScene.shapes_of` with arrows, in its order.
    """

    def __init__(self, scene: FormationScene, frame_id: str) -> None:
        n, k = len(scene.ids), len(scene.d_des)
        zeros = np.zeros((n, 3))
        identity = np.tile(np.eye(3), (n, 1, 1))
        shapes = scene.shapes_of(scene.frame(0.0, zeros, identity, np.zeros((n, 6))))
        cdr = CdrTemplate()
        cdr.u32(len(shapes))
        where: dict[str, list[tuple[int, int, int, int]]] = {}
        stamps = []
        for s in shapes:
            index = _marker(cdr, s, frame_id)
            stamps.append(index[0])
            where.setdefault(s.ns, []).append(index)
        self.cdr = cdr
        self.u32, self.f32, self.f64 = cdr.views()
        self.sec = np.asarray(stamps, dtype=np.intp)

        def column(ns: str, c: int) -> list[int]:
            return [w[c] for w in where.get(ns, [])]

        self.body_pose = _rows(column("bodies", 1), 7)  # (N, 7): position, quaternion
        self.label_position = _rows(column("labels", 1), 3)
        self.frame_points = _rows(column("frames", 2), 18)  # (N, 6·3): origin, x end, origin, y end, …
        self.force_points = _rows(column("forces", 2), 6)
        self.torque_points = _rows(column("torques", 2), 6)
        self.edge_points = _rows(column("edges", 2), 6)
        self.edge_colour = _rows(column("edges", 3), 4)
        self.ghost_position = _rows(column("desired", 1), 3)
        self.ghost_colour = _rows(column("desired", 3), 3)  # r, g, b; alpha stays the template's
        self.contact_position = _rows(column("contacts", 1), 3)
        self.contact_alpha = np.asarray(column("contacts", 3), dtype=np.intp) + 3  # a: clear unless touching
        if len(self.body_pose) != n or len(self.edge_points) != k:
            raise ValueError(f"scene: {len(self.body_pose)} bodies, {len(self.edge_points)} edges; expected {n}, {k}")

    def encode(self, ns: int, f: SceneFrame) -> bytes:
        """The MarkerArray of frame ``f``, every marker stamped ``ns`` (integer nanoseconds)."""
        sec, nsec = divmod(ns, 1_000_000_000)
        self.u32[self.sec] = sec
        self.u32[self.sec + 1] = nsec
        d = self.f64
        p = f.p
        d[self.body_pose] = np.concatenate([p, f.q], axis=1)
        d[self.label_position] = f.labels
        origin = p[:, None, :]
        d[self.frame_points] = np.stack([np.broadcast_to(origin, f.axis_ends.shape), f.axis_ends], axis=2).reshape(
            len(p), 18
        )
        d[self.force_points] = np.concatenate([p, f.tips[:, 0]], axis=1)
        d[self.torque_points] = np.concatenate([p, f.tips[:, 1]], axis=1)
        d[self.edge_points] = f.edge_ends.reshape(-1, 6)
        d[self.ghost_position] = f.ghosts
        self.f32[self.edge_colour] = f.edge_colours
        self.f32[self.ghost_colour] = f.edge_colours[:, :3]
        d[self.contact_position] = p
        self.f32[self.contact_alpha] = np.where(f.touching, CONTACT_COLOUR[3], 0.0)
        return self.cdr.message()


#: the fields of every edge in ``/formation/funnels``, in order: e [m²], its lower bound −C_col·ρ_e and
#: upper bound C_con·ρ_e [m²], ψ [-] and its bound ρ_ψ
FUNNEL_FIELDS = ("e", "e_lower", "e_upper", "psi", "rho_psi")


class FunnelsWire:
    """``/formation/funnels`` (std_msgs/Float64MultiArray): K edges × the given fields, as CDR bytes."""

    def __init__(self, edge_names: Sequence[str], fields: Sequence[str], rows: str = "edge") -> None:
        k, m = len(edge_names), len(fields)
        cdr = CdrTemplate()
        cdr.u32(2)  # layout.dim
        for label, size, stride in ((f"{rows} " + ",".join(edge_names), k, m * k), (",".join(fields), m, m)):
            cdr.string(label)
            cdr.u32(size)
            cdr.u32(stride)
        cdr.u32(0)  # layout.data_offset
        cdr.u32(k * m)
        start = cdr.f64([0.0] * (k * m))
        self.cdr = cdr
        _, _, self.f64 = cdr.views()
        self.data = slice(start, start + k * m)

    def encode(self, values: np.ndarray) -> bytes:
        """The message of ``values`` (K, fields), row-major."""
        self.f64[self.data] = values.ravel()
        return self.cdr.message()

"""VMC protocol over OSC (Virtual Motion Capture, protocol.vmc.info), the VTuber apps' wire.

Per frame, one OSC bundle (split into several when large, ``Apply`` in the last)::

    /VMC/Ext/OK        ,i        1                 (a model is loaded)
    /VMC/Ext/T         ,f        time (seconds)
    /VMC/Ext/Root/Pos  ,sfffffff "root" px py pz 0 0 0 1   (the head's shift from its neutral position)
    /VMC/Ext/Bone/Pos  ,sfffffff "Head" rx ry rz qx qy qz qw   (rest offset from the Neck, turn)
    /VMC/Ext/Bone/Pos  ,sfffffff "LeftEye"/"RightEye" rx ry rz qx qy qz qw  (rigs with eye-look shapes)
    /VMC/Ext/Blend/Val ,sf       name value        (one per shape or expression)
    /VMC/Ext/Blend/Apply                            (apply this frame's values)

Bone values are local (relative to the parent bone) in Unity's frame: left-handed, metres, +y
up, +z forward. A bone's position is its *rest* offset from its parent (the VMC sample sender
sends ``Transform.localPosition``), never a motion: EVMC4U applies bone positions by default
(``BonePositionSynchronize``), so anything else there moves the head onto the neck or the eyeballs
out of their sockets. livecap knows no avatar skeleton, so the offsets are ``rest_offsets`` when the
caller has the avatar's, else :data:`STANDARD_REST` (a typical adult humanoid, documented in
docs/protocol.md §4). The head's translation travels as the model root's position
(``/VMC/Ext/Root/Pos``, applied by EVMC4U's default ``RootPositionSynchronize``): the whole
avatar follows the head's sway instead of the neck stretching. Rotation and shift are relative to
the actor's neutral head pose, from livecap.core.headpose (which also removes the capture's axes).

Shape names: the rig's own; Perfect Sync (the 52 ARKit clips as Perfect Sync avatars name them,
``EyeBlinkLeft``, matched exactly by receivers such as VMC4B); or VRM 0.x / 1.0 expression
presets derived from the ARKit weights (transport.vrm).
"""

from __future__ import annotations

import socket
import struct
from collections.abc import Sequence

import numpy as np

from livecap.core.headpose import NeutralWindow
from livecap.core.headpose import to_unity as _mirror
from transport.arkit import ARKIT_NAMES, arkit_matrix
from transport.vrm import VrmExpressions, eye_rotations

PERFECT_SYNC_NAMES = [n[0].upper() + n[1:] for n in ARKIT_NAMES]
NAME_MODES = ("rig", "perfect-sync", "vrm0", "vrm1")

# Local rest positions (Unity metres) of the bones sent, when the avatar's own are not known: the
# Head ~8 cm above the Neck joint, the eyes 6.5 cm above and 6 cm in front of the Head joint, 64 mm
# apart (a typical adult's interpupillary distance). Unity's +x is the avatar's right.
STANDARD_REST = {"Head": (0.0, 0.08, 0.0), "LeftEye": (-0.032, 0.065, 0.06), "RightEye": (0.032, 0.065, 0.06)}
DEFAULT_PORT = 39539
MAX_DATAGRAM = 8192  # bundles beyond this are split: stays far below UDP's 64 KB and typical MTU reassembly limits


def osc_string(s: str) -> bytes:
    b = s.encode() + b"\0"
    return b + b"\0" * (-len(b) % 4)


def osc_message(address: str, tags: str, *args) -> bytes:
    out = [osc_string(address), osc_string("," + tags)]
    for t, a in zip(tags, args, strict=True):
        if t == "s":
            out.append(osc_string(a))
        elif t == "f":
            out.append(struct.pack(">f", a))
        elif t == "i":
            out.append(struct.pack(">i", a))
        else:
            raise ValueError(f"unsupported OSC type tag {t!r}")
    return b"".join(out)


def osc_bundle(messages: Sequence[bytes]) -> bytes:
    """An OSC bundle with the 'immediately' time tag."""
    return b"#bundle\0" + struct.pack(">Q", 1) + b"".join(struct.pack(">i", len(m)) + m for m in messages)


def to_unity(translation_mm: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """livecap head pose (right-handed mm) to Unity's left-handed metres."""
    t = np.asarray(translation_mm, dtype=float)
    q = np.asarray(quat_xyzw, dtype=float)
    return np.array([-t[0], t[1], t[2]]) / 1000.0, np.array([q[0], -q[1], -q[2], q[3]])


class VmcSink:
    """Send VMC bundles to ``host:port`` (default 127.0.0.1:39539). ``names``: ``rig`` (the rig's
    shape names), ``perfect-sync`` (ARKit, PascalCase, through the name mapping; ``arkit=True`` is
    the same), ``vrm0`` or ``vrm1`` (VRM expression presets from ``vrm_table``, default
    transport.vrm.VRM1_TABLE). The head pose is relative to the mean of the first ``neutral_frames``.
    ``rest_offsets``: the avatar's local rest positions of Head / LeftEye / RightEye (Unity metres);
    bones it leaves out take :data:`STANDARD_REST`."""

    def __init__(self, host: str = "127.0.0.1", port: int = DEFAULT_PORT, arkit: bool = False,
                 mapping: dict | None = None, where: str = "mapping", names: str = "rig",
                 vrm_table: dict | None = None, neutral_frames: int = 1,
                 rest_offsets: dict[str, Sequence[float]] | None = None) -> None:
        if names not in NAME_MODES:
            raise ValueError(f"VMC names {names!r}: one of {', '.join(NAME_MODES)}")
        self.target = (host, port)
        rest = {**STANDARD_REST, **(rest_offsets or {})}
        if set(rest) != set(STANDARD_REST) or any(np.shape(v) != (3,) or not np.all(np.isfinite(v))
                                                  for v in rest.values()):
            raise ValueError(f"rest_offsets: finite x, y, z (metres) for bones among {', '.join(STANDARD_REST)}")
        self.rest = {bone: tuple(map(float, v)) for bone, v in rest.items()}
        self.mode = "perfect-sync" if arkit and names == "rig" else names
        self.arkit = self.mode != "rig"
        self.vrm = VrmExpressions(int(self.mode[3]), vrm_table) if self.mode.startswith("vrm") else None
        self.neutral = NeutralWindow(neutral_frames)
        self.mapping = mapping
        self.where = where
        self._eyes_present: list[bool] = []
        self.sent = 0
        self.drops = 0
        self._names: Sequence[str] | None = None
        self._prefixes: list[bytes] = []
        self._M: np.ndarray | None = None
        self._ok = osc_message("/VMC/Ext/OK", "i", 1)
        self._apply = osc_message("/VMC/Ext/Blend/Apply", "")
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setblocking(False)

    def _prepare(self, names: Sequence[str]) -> None:
        self._names = names
        out_names = self.vrm.names if self.vrm else PERFECT_SYNC_NAMES if self.arkit else list(names)
        self._M = arkit_matrix(names, self.mapping, self.where)
        self._eyes_present = list(self._M.any(axis=1))
        # address, type tags and name are the same every frame: encode them once
        self._prefixes = [osc_string("/VMC/Ext/Blend/Val") + osc_string(",sf") + osc_string(n) for n in out_names]

    def datagrams(self, result) -> list[bytes]:
        if result.names is not self._names:
            self._prepare(result.names)
        w = np.asarray(result.weights, dtype=float)
        arkit = self._M @ w
        if self.arkit:
            w = self.vrm(arkit) if self.vrm else arkit
        rel_q, shift = self.neutral.relative(result.head_rotation, result.head_translation)
        q, p = _mirror(rel_q, shift)
        msgs = [self._ok, osc_message("/VMC/Ext/T", "f", float(result.timestamp)),
                osc_message("/VMC/Ext/Root/Pos", "sfffffff", "root", *map(float, p), 0.0, 0.0, 0.0, 1.0),
                osc_message("/VMC/Ext/Bone/Pos", "sfffffff", "Head", *self.rest["Head"], *map(float, q))]
        eyes = eye_rotations(arkit, self._eyes_present)
        if eyes is not None:
            msgs += [osc_message("/VMC/Ext/Bone/Pos", "sfffffff", bone, *self.rest[bone], *map(float, eq))
                     for bone, eq in zip(("LeftEye", "RightEye"), eyes, strict=True)]
        vals = np.asarray(w, dtype=">f4").tobytes()
        msgs += [pre + vals[4 * i:4 * i + 4] for i, pre in enumerate(self._prefixes)]
        msgs.append(self._apply)
        out, chunk, size = [], [], 16
        for m in msgs:
            if chunk and size + 4 + len(m) > MAX_DATAGRAM:
                out.append(osc_bundle(chunk))
                chunk, size = [], 16
            chunk.append(m)
            size += 4 + len(m)
        out.append(osc_bundle(chunk))
        return out

    def publish(self, result) -> None:
        for dgram in self.datagrams(result):
            try:
                self.sock.sendto(dgram, self.target)
            except OSError:  # would block, or ICMP port unreachable: UDP is fire-and-forget
                self.drops += 1
                return
        self.sent += 1

    def stats(self) -> dict:
        return {"sent": self.sent, "drops": self.drops}

    def close(self) -> None:
        self.sock.close()

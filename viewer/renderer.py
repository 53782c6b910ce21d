"""GPU blendshape preview of a Rig (draws only: weights, head pose and markers in, pixels out).

The rig goes to the GPU once: neutral as a vertex buffer, every field (delta shapes, in-between
residuals, corrective deltas; Lewis et al. 2014 §3.1-3.3) in one storage buffer. Per frame only
the active coefficients travel: the shape weights themselves, and the few nonlinear ones computed
on the CPU in O(shapes) -- the in-betweens' hat functions and the correctives' weight products.
The sum over fields runs in the vertex shader (transform feedback), vertex normals of the
deformed surface in a second vertex pass, then the lit draw and the marker overlay. Fields and
mesh adjacency live in float/integer textures and the active list in a uniform block: on Mesa's
llvmpipe that is about ten times faster than storage buffers (measured, benchmarks/viewer_fps.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from livecap.core.markers import MarkerLayout
from livecap.core.rig import Rig
from viewer import shaders
from viewer.errors import create_context
from viewer.scene import Camera, project, transform

SOURCE_COLOUR = (1.0, 0.82, 0.10)  # actor markers, retargeted onto the rig (yellow)
SITE_COLOUR = (0.15, 0.80, 1.00)  # rig marker sites at the solved weights (cyan)
LINK_COLOUR = (1.0, 0.25, 0.30)  # source -> site: the residual the solver left (red)
SKIN = (0.80, 0.62, 0.52)


def field_coefficients(rig: Rig, weights: np.ndarray) -> np.ndarray:
    """Coefficient of every field for ``weights``: shapes, then in-betweens, then correctives.

    Matches :meth:`Rig.evaluate` term by term (``face = neutral + sum_i c_i F_i``).
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (rig.n_shapes,):
        raise ValueError(f"expected {rig.n_shapes} weights, got shape {w.shape}")
    ib = [float(i.hat(w[i.shape])) for i in rig.inbetweens]
    co = [float(np.prod(w[list(c.shapes)])) for c in rig.correctives]
    return np.concatenate([w, ib, co])


def _data_texture(ctx, rows: np.ndarray, dtype: str):
    """An (N x c) array as a c-channel texture, TEX_WIDTH texels per row (element i at (i % W, i / W))."""
    n, comps = rows.shape
    width = shaders.TEX_WIDTH
    height = max(1, -(-n // width))
    if height > ctx.info["GL_MAX_TEXTURE_SIZE"]:
        raise ValueError(f"rig too large for the preview: {n} texels need {height} rows of {width}")
    data = np.zeros((height * width, comps), dtype=rows.dtype)
    data[:n] = rows
    return ctx.texture((width, height), comps, data.tobytes(), dtype=dtype)


def one_ring(triangles: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR of each vertex's incident triangles as the other two corners in winding order."""
    t = np.asarray(triangles, dtype=np.int64)
    centre = t.ravel()  # corner k of triangle j
    others = np.stack([t[:, [1, 2]], t[:, [2, 0]], t[:, [0, 1]]], axis=1).reshape(-1, 2)
    order = np.argsort(centre, kind="stable")
    start = np.zeros(n_vertices + 1, dtype=np.int32)
    np.cumsum(np.bincount(centre, minlength=n_vertices), out=start[1:])
    return start, others[order].astype(np.int32)


@dataclass
class Overlay:
    """What the overlay drew last frame (display space), for captions and tests."""

    sources: np.ndarray  # k x 3 valid source markers
    sites: np.ndarray  # n x 3 fitted sites
    rms_mm: float  # RMS distance source -> site over valid markers (rig units)


class Renderer:
    """Offscreen renderer of one rig; ``render(...)`` returns a BGR uint8 image (OpenCV order).

    ``deformation="gpu"`` (default) deforms on the GPU; ``"cpu"`` evaluates the rig with numpy and
    uploads positions and normals every frame (the baseline the benchmark compares against).
    """

    def __init__(self, rig: Rig, layout: MarkerLayout | None = None, size: tuple[int, int] = (640, 480),
                 ctx=None, samples: int = 0, camera: Camera | None = None, deformation: str = "gpu") -> None:
        import moderngl


        if deformation not in ("gpu", "cpu"):
            raise ValueError(f"deformation must be 'gpu' or 'cpu', not {deformation!r}")
        self.rig, self.layout, self.size, self.deformation = rig, layout, tuple(size), deformation
        self.ctx = ctx or create_context()
        self.camera = camera or Camera.frame(rig.neutral, self.aspect)
        ctx = self.ctx
        V = rig.n_vertices
        self._V = V
        self._neutral = ctx.buffer(rig.neutral.astype(np.float32).tobytes())

        fields = [rig.deltas] + [i.residual[None] for i in rig.inbetweens] + [c.delta[None] for c in rig.correctives]
        fields_arr = np.concatenate(fields).astype(np.float32)
        self.n_fields = F = len(fields_arr)
        n4 = max(1, -(-F // 4))
        if 32 * n4 > ctx.info["GL_MAX_UNIFORM_BLOCK_SIZE"]:
            raise ValueError(f"rig has {F} fields (shapes + in-betweens + correctives); the preview's uniform "
                             f"block holds at most {ctx.info['GL_MAX_UNIFORM_BLOCK_SIZE'] // 32 * 4}")
        self._fields = _data_texture(ctx, np.c_[fields_arr.reshape(-1, 3), np.zeros(F * V, np.float32)], "f4")
        self._active = ctx.buffer(reserve=32 * n4)
        self._active_idx = np.zeros(4 * n4, np.int32)
        self._active_coef = np.zeros(4 * n4, np.float32)
        start, ring = one_ring(rig.triangles, V)
        self._ring_span = _data_texture(ctx, np.c_[start[:-1], np.diff(start)].astype(np.int32), "i4")
        self._ring = _data_texture(ctx, ring.reshape(-1, 2), "i4")
        rows = -(-V // shaders.TEX_WIDTH)
        # feedback buffers padded to whole texture rows so they copy straight into a texture
        self.positions_buffer = ctx.buffer(reserve=12 * rows * shaders.TEX_WIDTH)
        self.normals_buffer = ctx.buffer(reserve=12 * V)
        self._pos_tex = ctx.texture((shaders.TEX_WIDTH, rows), 3, dtype="f4")
        for tex in (self._fields, self._ring_span, self._ring, self._pos_tex):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._tris = ctx.buffer(rig.triangles.astype(np.int32).tobytes())

        self._deform = ctx.program(vertex_shader=shaders.DEFORM_VS.format(n4=n4, width=shaders.TEX_WIDTH),
                                   varyings=["out_pos"])
        self._deform["n_vertices"].value = V
        self._deform["fields"].value = 0
        self._deform["Active"].binding = 0
        self._deform_vao = ctx.vertex_array(self._deform, [(self._neutral, "3f", "in_neutral")])
        self._normals = ctx.program(vertex_shader=shaders.NORMALS_VS.format(width=shaders.TEX_WIDTH),
                                    varyings=["out_normal"])
        for unit, name in enumerate(("pos", "ring_span", "ring")):
            self._normals[name].value = unit
        self._normals_vao = ctx.vertex_array(self._normals, [])
        self._mesh = ctx.program(vertex_shader=shaders.MESH_VS, fragment_shader=shaders.MESH_FS)
        self._mesh["albedo"].value = SKIN
        self._mesh_vao = ctx.vertex_array(
            self._mesh, [(self.positions_buffer, "3f", "in_pos"), (self.normals_buffer, "3f", "in_normal")],
            index_buffer=self._tris, index_element_size=4)
        self._overlay = ctx.program(vertex_shader=shaders.OVERLAY_VS, fragment_shader=shaders.OVERLAY_FS)
        n = layout.n_markers if layout is not None else 0
        self._overlay_buf = ctx.buffer(reserve=max(1, 4 * n) * 24)
        self._overlay_vao = ctx.vertex_array(self._overlay, [(self._overlay_buf, "3f 3f", "in_pos", "in_colour")])
        self._sites_rig = layout.marker_rig(rig) if layout is not None else None

        w, h = self.size
        self._fbo = ctx.framebuffer(ctx.renderbuffer((w, h), 4), ctx.depth_renderbuffer((w, h)))
        self._msaa = None
        if samples and samples > 1:
            self._msaa = ctx.framebuffer(ctx.renderbuffer((w, h), 4, samples=samples),
                                         ctx.depth_renderbuffer((w, h), samples=samples))
        self.background = (0.11, 0.12, 0.14)
        self.point_size = max(4.0, round(h / 90))
        self.last_overlay: Overlay | None = None
        if deformation == "cpu":
            from viewer.cpu import CpuDeformer

            self._cpu = CpuDeformer(rig)

    # ------------------------------------------------------------------ geometry
    @property
    def aspect(self) -> float:
        return self.size[0] / self.size[1]

    def view_projection(self) -> np.ndarray:
        return self.camera.view_projection(self.aspect)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (x right, y down) of display-space points, as the GPU draws them."""
        return project(self.view_projection(), points, self.size)

    def deform(self, weights: np.ndarray) -> None:
        """Deformed positions and normals of ``weights`` into the GPU buffers the mesh is drawn from."""
        if self.deformation == "cpu":
            pos, nrm = self._cpu(weights)
            self.positions_buffer.write(pos.tobytes())
            self.normals_buffer.write(nrm.tobytes())
            return
        import moderngl

        self._fbo.use()  # EGL standalone contexts have no default framebuffer: any draw, even TF, needs one
        c = field_coefficients(self.rig, weights) if self.n_fields else np.zeros(0)
        idx = np.flatnonzero(c)
        k = len(idx)
        if k:
            self._active_idx[:k] = idx
            self._active_coef[:k] = c[idx]
            self._active.write(self._active_idx.tobytes() + self._active_coef.tobytes())
        self._deform["n_active"].value = k
        self._active.bind_to_uniform_block(0)
        self._fields.use(0)
        self._deform_vao.transform(self.positions_buffer, moderngl.POINTS, vertices=self._V)
        self._pos_tex.write(self.positions_buffer)  # GPU-side copy: buffer -> texture (pixel unpack)
        self._pos_tex.use(0)
        self._ring_span.use(1)
        self._ring.use(2)
        self._normals_vao.transform(self.normals_buffer, moderngl.POINTS, vertices=self._V)

    def read_positions(self) -> np.ndarray:
        """The deformed vertices the GPU holds (V x 3 float32), read back from the feedback buffer."""
        return np.frombuffer(self.positions_buffer.read(size=12 * self._V), dtype=np.float32).reshape(self._V, 3)

    def read_normals(self) -> np.ndarray:
        return np.frombuffer(self.normals_buffer.read(), dtype=np.float32).reshape(self._V, 3)

    def sites(self, weights: np.ndarray) -> np.ndarray:
        """The rig's marker sites at ``weights`` (rig frame): what the solver fitted."""
        if self._sites_rig is None:
            raise ValueError("this renderer has no marker layout")
        return self._sites_rig.evaluate(weights)

    # ------------------------------------------------------------------ drawing
    def render(self, weights: np.ndarray, model: np.ndarray | None = None, markers: np.ndarray | None = None,
               valid: np.ndarray | None = None, show_sites: bool = True) -> np.ndarray:
        """BGR image of the rig at ``weights`` under the rig-to-display ``model`` transform (4x4).

        ``markers``: source markers in the rig frame (n x 3, layout order; see
        ``viewer.compose.retarget_markers``), drawn with a line to the fitted site of each.
        """
        import moderngl

        ctx = self.ctx
        model = np.eye(4) if model is None else np.asarray(model, dtype=np.float64)
        self.deform(weights)
        vp = self.view_projection()
        target = self._msaa or self._fbo
        target.use()
        ctx.clear(*self.background, 1.0)
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        self._mesh["model"].write(model.T.astype(np.float32).tobytes())
        self._mesh["view_proj"].write(vp.T.astype(np.float32).tobytes())
        self._mesh["eye"].value = tuple(self.camera.eye)
        self._mesh_vao.render(moderngl.TRIANGLES)
        self._draw_overlay(weights, model, markers, valid, vp, show_sites)
        if self._msaa is not None:
            ctx.copy_framebuffer(self._fbo, self._msaa)
        w, h = self.size
        rgba = np.frombuffer(self._fbo.read(components=4), dtype=np.uint8).reshape(h, w, 4)  # RGBA reads fastest
        return np.ascontiguousarray(rgba[::-1, :, 2::-1])

    def _draw_overlay(self, weights, model, markers, valid, vp, show_sites) -> None:
        import moderngl

        self.last_overlay = None
        if self._sites_rig is None or (markers is None and not show_sites):
            return
        sites = transform(model, self.sites(weights))
        n = len(sites)
        valid = np.ones(n, bool) if valid is None else np.asarray(valid, dtype=bool)
        verts: list[np.ndarray] = []
        if markers is not None:
            src = transform(model, np.asarray(markers, dtype=np.float64))[valid]
            links = np.stack([src, sites[valid]], axis=1).reshape(-1, 3)
            verts.append(np.c_[links, np.tile(LINK_COLOUR, (len(links), 1))])
        n_lines = sum(len(v) for v in verts)
        if show_sites:
            verts.append(np.c_[sites, np.tile(SITE_COLOUR, (n, 1))])
        if markers is not None:
            verts.append(np.c_[src, np.tile(SOURCE_COLOUR, (len(src), 1))])
            rms = float(np.sqrt(np.mean(np.sum((src - sites[valid]) ** 2, 1)))) if len(src) else float("nan")
            self.last_overlay = Overlay(src, sites, rms)
        else:
            self.last_overlay = Overlay(np.zeros((0, 3)), sites, float("nan"))
        data = np.concatenate(verts).astype(np.float32)
        if not len(data):
            return
        self._overlay_buf.write(data.tobytes())
        self.ctx.disable(moderngl.DEPTH_TEST)  # overlay stays visible on top of the face
        self.ctx.enable(moderngl.PROGRAM_POINT_SIZE)
        self._overlay["view_proj"].write(vp.T.astype(np.float32).tobytes())
        self._overlay["point_size"].value = self.point_size
        if n_lines:
            self._overlay["round_points"].value = False
            self._overlay_vao.render(moderngl.LINES, vertices=n_lines)
        self._overlay["round_points"].value = True
        self._overlay_vao.render(moderngl.POINTS, vertices=len(data) - n_lines, first=n_lines)

    def release(self) -> None:
        for obj in (self._mesh_vao, self._overlay_vao, self._deform_vao, self._normals_vao, self._fbo):
            obj.release()

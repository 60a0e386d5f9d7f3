"""Ground-truth renderer of the synthetic scenes: textured, Lambert-shaded triangle meshes drawn
with OpenGL (moderngl, headless llvmpipe), 4x multisampled. Independent of the Gaussian
rasterizer on purpose: the benchmark must not be rendered by the thing it measures. A rig camera's
image carries its exposure (SynthScene.exposure_of): the held-out ground truth is what it recorded."""

from __future__ import annotations

import numpy as np

from atgs.cameras import Camera
from atgs.data.synth.scene import Mesh, SynthScene, expose

_VS = """
#version 330 core
uniform mat4 u_proj_view;
in vec3 in_pos;
in vec3 in_nrm;
in vec2 in_uv;
out vec3 v_nrm;
out vec2 v_uv;
void main() {
    v_nrm = in_nrm;
    v_uv = in_uv;
    gl_Position = u_proj_view * vec4(in_pos, 1.0);
}
"""

_FS = """
#version 330 core
uniform sampler2D u_tex;
uniform vec3 u_light;
uniform float u_even;  // 0: Lambert; towards 1: the even light of a stage's walls (SceneObject "even_light")
in vec3 v_nrm;
in vec2 v_uv;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_nrm);
    float key = max(dot(n, u_light), 0.0);
    float fill = max(dot(n, normalize(vec3(-0.5, 0.6, 0.3))), 0.0);
    float shade = mix(0.42 + 0.5 * key + 0.15 * fill, 0.85, u_even);
    f_color = vec4(min(texture(u_tex, v_uv).rgb * shade, vec3(1.0)), 1.0);
}
"""

_DEPTH_VS = """
#version 330 core
uniform mat4 u_proj_view;
uniform mat4 u_view;
in vec3 in_pos;
out float v_z;
void main() {
    v_z = -(u_view * vec4(in_pos, 1.0)).z;  // OpenGL cameras look down -z; OpenCV depth is +z
    gl_Position = u_proj_view * vec4(in_pos, 1.0);
}
"""

_DEPTH_FS = """
#version 330 core
in float v_z;
out float f_depth;
void main() { f_depth = v_z; }
"""

NEAR, FAR = 0.05, 60.0


def _interleave(mesh: Mesh) -> np.ndarray:
    v = np.concatenate([mesh.positions, mesh.normals, mesh.uvs], axis=1).astype("f4")
    return np.ascontiguousarray(v)


class MeshRenderer:
    """Renders a :class:`SynthScene` from any :class:`Camera` into (H,W,3) uint8 images."""

    def __init__(self, scene: SynthScene, width: int, height: int, samples: int = 4) -> None:
        import moderngl

        try:
            from atgs.headless_gl import create_headless_context

            self.ctx = create_headless_context()
        except ImportError:  # the viewer's helper module is optional
            self.ctx = moderngl.create_standalone_context(backend="egl", require=330)
        ctx = self.ctx
        self.scene, self.width, self.height = scene, width, height
        self.prog = ctx.program(vertex_shader=_VS, fragment_shader=_FS)
        self.prog["u_light"].value = tuple(float(x) for x in scene.light_dir)
        self.textures = []
        for img in scene.textures:
            tex = ctx.texture((img.shape[1], img.shape[0]), 3, np.ascontiguousarray(img).tobytes())
            tex.build_mipmaps()
            tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            tex.repeat_x = tex.repeat_y = True
            tex.anisotropy = 1.0  # trilinear only: anisotropic filtering costs 2-4x on llvmpipe
            self.textures.append(tex)
        self.vaos, self._ibos = [], []
        for obj in scene.objects:
            mesh = obj.mesh
            vbo = ctx.buffer(reserve=len(mesh.positions) * 8 * 4, dynamic=not obj.static)
            ibo = ctx.buffer(np.ascontiguousarray(mesh.faces.astype("i4")).tobytes())
            vao = ctx.vertex_array(self.prog, [(vbo, "3f 3f 2f", "in_pos", "in_nrm", "in_uv")], index_buffer=ibo)
            self.vaos.append((obj, vbo, vao))
            self._ibos.append(ibo)
        samples = min(samples, ctx.max_samples)
        self.msaa = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), 4, samples=samples)],
                                    depth_attachment=ctx.depth_renderbuffer((width, height), samples=samples))
        self.resolve = ctx.framebuffer(color_attachments=[ctx.renderbuffer((width, height), 4)])
        self._depth: tuple | None = None  # program, vertex arrays, framebuffer: made on first use
        self._frame: int | None = None

    def set_frame(self, frame: int) -> None:
        """Upload the world-space geometry of ``frame`` (static meshes once)."""
        first = self._frame is None
        meshes = self.scene.meshes_at(frame)
        for (obj, vbo, _), (_, mesh) in zip(self.vaos, meshes):
            if first or not obj.static:
                vbo.write(_interleave(mesh))
        self._frame = frame

    def render(self, cam: Camera, exposed: bool = True) -> np.ndarray:
        """What ``cam`` records: the rendered image under the camera's exposure
        (SynthScene.exposure_of, by camera name; ``exposed=False``: as rendered)."""
        import moderngl

        if self._frame is None:
            raise RuntimeError("call set_frame() first")
        ctx = self.ctx
        self.msaa.use()
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        ctx.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        pv = cam.gl_projection(NEAR, FAR) @ cam.gl_view()
        self.prog["u_proj_view"].write(pv.T.astype("f4").tobytes())  # GLSL is column major
        for obj, _, vao in self.vaos:
            self.textures[obj.texture].use(0)
            self.prog["u_tex"].value = 0
            self.prog["u_even"].value = float(obj.params.get("even_light", 0.0))
            vao.render(moderngl.TRIANGLES)
        ctx.copy_framebuffer(self.resolve, self.msaa)
        data = self.resolve.read(components=3, alignment=1)
        img = np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3)
        img = img[::-1].copy()  # OpenGL rows go bottom-up
        return expose(img, *self.scene.exposure_of(cam.name)) if exposed else img

    def render_depth(self, cam: Camera) -> np.ndarray:
        """True depth (H,W) float32: the OpenCV z of the nearest surface at each pixel center
        (no multisampling), 0 where no surface is hit."""
        import moderngl

        if self._frame is None:
            raise RuntimeError("call set_frame() first")
        ctx = self.ctx
        if self._depth is None:
            prog = ctx.program(vertex_shader=_DEPTH_VS, fragment_shader=_DEPTH_FS)
            vaos = [ctx.vertex_array(prog, [(vbo, "3f 20x", "in_pos")], index_buffer=ibo)
                    for (_, vbo, _), ibo in zip(self.vaos, self._ibos)]
            fbo = ctx.framebuffer(color_attachments=[ctx.renderbuffer((self.width, self.height), 1, dtype="f4")],
                                  depth_attachment=ctx.depth_renderbuffer((self.width, self.height)))
            self._depth = (prog, vaos, fbo)
        prog, vaos, fbo = self._depth
        fbo.use()
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.disable(moderngl.CULL_FACE)
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        prog["u_proj_view"].write((cam.gl_projection(NEAR, FAR) @ cam.gl_view()).T.astype("f4").tobytes())
        prog["u_view"].write(cam.gl_view().T.astype("f4").tobytes())
        for vao in vaos:
            vao.render(moderngl.TRIANGLES)
        data = fbo.read(components=1, dtype="f4", alignment=1)
        return np.frombuffer(data, np.float32).reshape(self.height, self.width)[::-1].copy()

    def release(self) -> None:
        self.ctx.release()

// The WebGL2 renderer, with the semantics of the CPU reference (crates/7-output/cpsl-render):
// per layer the inverse plane-induced homography (for a mesh layer, its triangles rasterised
// into a source map first, as cpsl-render-gpu does), bilinear premultiplied sampling with a
// transparent border, front-to-back compositing (paper eq. 2), then the Dynamic Pixel Strip
// (paper eq. 4) guided by the Edge-Depth Cache. The layer pictures are converted from
// Y'CbCr (BT.709, limited range, colour over alpha) in the shader exactly as cpsl-codec's
// `unstack` does, so the browser's own colour conversion never enters.

import { type Camera, type Pose, horizonClip, layerInverse, meshTriangles, stripWidth } from "./pose.js";
import type { SideFrame } from "./package.js";

/** Most layers per frame. */
export const MAX_LAYERS = 16;
/** Triangles per row of the homography texture (3 texels each). */
const TRIS_PER_ROW = 1024;

const VERT = `#version 300 es
void main() {
  vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
  gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}`;

// Shared by both passes: one layer texel (premultiplied RGBA, 0..255) from the planes.
const TEXEL = `
precision highp float;
precision highp int;
precision highp sampler2DArray;
uniform sampler2DArray uY;
uniform sampler2DArray uU;
uniform sampler2DArray uV;
uniform ivec2 uSize;      // layer (frame) size
uniform int uHalf;        // coded height of one half: alpha rows start here
uniform mat3 uH[${MAX_LAYERS}];
uniform int uStream[${MAX_LAYERS}];
uniform int uScale[${MAX_LAYERS}];  // downscale factor of layer k's stream
uniform int uLayers;
uniform bool uCubic;      // Catmull-Rom instead of bilinear sampling
uniform vec4 uPlane[${MAX_LAYERS}];  // inverse depth a x + b y + c of slanted layer k, clip margin
uniform int uMesh[${MAX_LAYERS}];    // mesh layer k's slice of uMaps, -1 for a plane
uniform highp sampler2DArray uMaps;  // per mesh layer and pixel: its triangle, coverage
uniform highp sampler2D uTriH;       // per triangle its inverse homography, 3 rows of RGBA32F

float q8(float v) { return clamp(floor(v + 0.5), 0.0, 255.0); }

// One texel of stream s (its colour half is rows high), as cpsl-codec unstack does.
vec4 coded(int s, ivec2 t, int rows) {
  float ya = texelFetch(uY, ivec3(t.x, t.y + rows, s), 0).r * 255.0;
  float a = q8((ya - 16.0) * 255.0 / 219.0);
  if (a == 0.0) return vec4(0.0);
  float luma = (texelFetch(uY, ivec3(t, s), 0).r * 255.0 - 16.0) / 219.0;
  ivec2 c = t / 2;
  float cb = (texelFetch(uU, ivec3(c, s), 0).r * 255.0 - 128.0) / 224.0;
  float cr = (texelFetch(uV, ivec3(c, s), 0).r * 255.0 - 128.0) / 224.0;
  const float KR = 0.2126, KB = 0.0722, KG = 1.0 - 0.2126 - 0.0722;
  float r = luma + 2.0 * (1.0 - KR) * cr;
  float b = luma + 2.0 * (1.0 - KB) * cb;
  float g = (luma - KR * r - KB * b) / KG;
  return vec4(min(vec3(q8(r * 255.0), q8(g * 255.0), q8(b * 255.0)), vec3(a)), a);
}

// Layer k's texel at frame pixel t. A stream coded at downscale f is upsampled bilinearly
// as cpsl-codec's scale::upscale does: pixel x reads (x + 0.5) / f - 0.5, clamped.
vec4 texel(int k, ivec2 t) {
  if (t.x < 0 || t.y < 0 || t.x >= uSize.x || t.y >= uSize.y) return vec4(0.0);
  // Beyond a slanted plane's horizon coded texels are noise (Layer::clip_to_geometry).
  vec4 p = uPlane[k];
  if (p.x * float(t.x) + p.y * float(t.y) + p.z <= p.w) return vec4(0.0);
  int s = uStream[k];
  int f = uScale[k];
  if (f == 1) return coded(s, t, uHalf);
  ivec2 size = (uSize + f - 1) / f;
  int rows = size.y + (size.y & 1);
  vec2 u = max((vec2(t) + 0.5) / float(f) - 0.5, vec2(0.0));
  vec2 w = u - floor(u);
  ivec2 a = min(ivec2(floor(u)), size - 1);
  ivec2 b = min(a + 1, size - 1);
  vec4 v = mix(mix(coded(s, a, rows), coded(s, ivec2(b.x, a.y), rows), w.x),
               mix(coded(s, ivec2(a.x, b.y), rows), coded(s, b, rows), w.x), w.y);
  return floor(v + 0.5);
}

// Target pixel -> source position of layer k; false where its surface is not visible.
bool warp(int k, vec2 px, out vec2 src) {
  if (uMesh[k] >= 0) {
    vec4 m = texelFetch(uMaps, ivec3(ivec2(px), uMesh[k]), 0);
    if (m.z <= 0.0) return false;
    int t = int(m.x);
    ivec2 at = ivec2((t % ${TRIS_PER_ROW}) * 3, t / ${TRIS_PER_ROW});
    vec3 p = vec3(px, 1.0);
    vec3 h = vec3(dot(texelFetch(uTriH, at, 0).xyz, p), dot(texelFetch(uTriH, at + ivec2(1, 0), 0).xyz, p),
                  dot(texelFetch(uTriH, at + ivec2(2, 0), 0).xyz, p));
    if (h.z <= 0.0) return false;
    src = h.xy / h.z;
    return true;
  }
  vec3 h = uH[k] * vec3(px, 1.0);
  if (h.z <= 0.0) return false;
  src = h.xy / h.z;
  return true;
}
`;

const COMPOSITE = `#version 300 es
${TEXEL}
out vec4 outColor;

// Catmull-Rom weights of the taps at -1, 0, 1, 2 for fraction f.
vec4 cubicWeights(float f) {
  float f2 = f * f, f3 = f2 * f;
  return 0.5 * vec4(-f3 + 2.0 * f2 - f, 3.0 * f3 - 5.0 * f2 + 2.0, -3.0 * f3 + 4.0 * f2 + f, f3 - f2);
}

// Catmull-Rom sample of layer k around texel i0 at fraction a, rounded to 0..255, colour at most
// alpha (as the CPU renderer's and cpsl-render-gpu's).
vec4 cubic(int k, ivec2 i0, vec2 a) {
  vec4 wx = cubicWeights(a.x), wy = cubicWeights(a.y);
  vec4 acc = vec4(0.0);
  for (int j = 0; j < 4; j++) {
    int y = i0.y + j - 1;
    acc += wy[j] * (wx.x * texel(k, ivec2(i0.x - 1, y)) + wx.y * texel(k, ivec2(i0.x, y)) +
                    wx.z * texel(k, ivec2(i0.x + 1, y)) + wx.w * texel(k, ivec2(i0.x + 2, y)));
  }
  float al = clamp(floor(acc.a + 0.5), 0.0, 255.0);
  return vec4(min(max(floor(acc.rgb + 0.5), vec3(0.0)), vec3(al)), al);
}
void main() {
  vec2 px = floor(gl_FragCoord.xy);
  vec4 o = vec4(0.0);
  float t = 1.0;
  for (int k = 0; k < uLayers; k++) {
    vec2 s;
    if (!warp(k, px, s)) continue;
    // Positions rounded to 1/256 px and bilinear weights as the CPU renderer's fixed point.
    vec2 fi = floor(s * 256.0 + 0.5);
    vec2 f0 = floor(fi / 256.0);
    vec2 w = (fi - f0 * 256.0) / 256.0;
    ivec2 i0 = ivec2(f0);
    if (i0.x < -1 || i0.y < -1 || i0.x >= uSize.x || i0.y >= uSize.y) continue;
    vec4 p00 = texel(k, i0), p01 = texel(k, i0 + ivec2(1, 0));
    vec4 p10 = texel(k, i0 + ivec2(0, 1)), p11 = texel(k, i0 + ivec2(1, 1));
    vec4 v;
    if (uCubic) {
      // As the CPU renderer: only where one of the central four texels is covered.
      if (p00 + p01 + p10 + p11 == vec4(0.0)) continue;
      v = cubic(k, i0, w);
    } else {
      v = floor(mix(mix(p00, p01, w.x), mix(p10, p11, w.x), w.y) + 0.5);
    }
    if (v.a <= 0.0) continue;
    o += t * v;
    t *= 1.0 - v.a / 255.0;
    if (t <= 0.0) break;
  }
  float a = q8(o.a);
  outColor = vec4(min(vec3(q8(o.r), q8(o.g), q8(o.b)), vec3(a)), a) / 255.0;
}`;

const DPS = `#version 300 es
${TEXEL}
uniform sampler2D uImage;     // the composite, RGBA8
uniform sampler2D uOffsets;   // RG32F, MAX_LAYERS x MAX_LAYERS: mean EDC offsets per pair
uniform float uLogDepth[${MAX_LAYERS}];
uniform int uReach;
out vec4 outColor;

vec4 img(ivec2 p) { return texelFetch(uImage, p, 0) * 255.0; }
bool covered(ivec2 p) { return img(p).a >= 128.0; }

float alphaAt(int k, vec2 s) {
  vec2 f = floor(s);
  vec2 a = s - f;
  ivec2 i = ivec2(f);
  float t00 = texel(k, i).a, t10 = texel(k, i + ivec2(1, 0)).a;
  float t01 = texel(k, i + ivec2(0, 1)).a, t11 = texel(k, i + ivec2(1, 1)).a;
  return mix(mix(t00, t10, a.x), mix(t01, t11, a.x), a.y) / 255.0;
}

int visibleLayer(ivec2 p) {
  for (int k = 0; k < uLayers; k++) {
    vec2 s;
    if (!warp(k, vec2(p), s)) continue;
    if (!(s.x > -1.0 && s.y > -1.0 && s.x < float(uSize.x) && s.y < float(uSize.y))) continue;
    if (alphaAt(k, s) >= 0.5) return k;
  }
  return -1;
}

bool nearAlong(ivec2 p, ivec2 d, ivec2 size) {
  for (int step = 1; step <= uReach; step++) {
    ivec2 q = p + d * step;
    if (q.x < 0 || q.y < 0 || q.x >= size.x || q.y >= size.y) return false;
    if (covered(q)) return true;
  }
  return false;
}

void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  ivec2 size = textureSize(uImage, 0);
  vec4 here = img(p);
  outColor = here / 255.0;
  if (here.a >= 128.0) return;
  if (!((nearAlong(p, ivec2(1, 0), size) && nearAlong(p, ivec2(-1, 0), size)) ||
        (nearAlong(p, ivec2(0, 1), size) && nearAlong(p, ivec2(0, -1), size)))) return;
  const ivec2 DIRS[8] = ivec2[8](ivec2(1, 0), ivec2(-1, 0), ivec2(0, 1), ivec2(0, -1),
                                 ivec2(1, 1), ivec2(-1, -1), ivec2(1, -1), ivec2(-1, 1));
  float len[8];
  ivec2 at[8];
  int lay[8];
  bool hit[8];
  for (int d = 0; d < 8; d++) {
    hit[d] = false;
    lay[d] = -1;
    for (int step = 1; step <= uReach; step++) {
      ivec2 q = p + DIRS[d] * step;
      if (q.x < 0 || q.y < 0 || q.x >= size.x || q.y >= size.y) break;
      if (covered(q)) {
        int k = visibleLayer(q);
        if (k >= 0) {
          len[d] = length(vec2(DIRS[d])) * float(step);
          at[d] = q;
          lay[d] = k;
          hit[d] = true;
        }
        break;
      }
    }
  }
  if (!((hit[0] && hit[1]) || (hit[2] && hit[3]) || (hit[4] && hit[5]) || (hit[6] && hit[7]))) return;
  int f = ${MAX_LAYERS}, b = -1;
  for (int d = 0; d < 8; d++) if (hit[d]) { f = min(f, lay[d]); b = max(b, lay[d]); }
  // Nearest side of each: the first in direction order among equals, as the CPU does.
  float df = 1e9, db = 1e9;
  ivec2 qf = p, qb = p;
  for (int d = 0; d < 8; d++) {
    if (hit[d] && lay[d] == f && len[d] < df) { df = len[d]; qf = at[d]; }
    if (hit[d] && lay[d] == b && len[d] < db) { db = len[d]; qb = at[d]; }
  }
  float gamma = 0.0;
  if (f != b) {
    gamma = df / (df + db);
    vec2 off = texelFetch(uOffsets, ivec2(f, b), 0).rg;
    float zf = uLogDepth[f], zb = uLogDepth[b];
    float r = clamp((zb + off.y - zf - off.x) / (zb - zf), 0.0, 2.0);
    gamma = clamp(0.5 + (gamma - 0.5) * (1.0 + r), 0.0, 1.0);
  }
  vec4 cf = img(qf), cb = img(qb);
  vec3 strip = (1.0 - gamma) * (cf.rgb / max(cf.a, 1.0) * 255.0) + gamma * (cb.rgb / max(cb.a, 1.0) * 255.0);
  float t = 1.0 - here.a / 255.0;
  outColor = vec4(clamp(floor(here.rgb + t * strip + 0.5), 0.0, 255.0) / 255.0, 1.0);
}`;

const PRESENT = `#version 300 es
precision highp float;
uniform sampler2D uImage;
uniform ivec2 uView;      // where this eye's image starts on the canvas (x) and its size
uniform ivec2 uViewSize;
out vec4 outColor;
void main() {
  ivec2 size = textureSize(uImage, 0);
  vec2 rel = (gl_FragCoord.xy - vec2(uView)) / vec2(uViewSize);
  ivec2 p = ivec2(rel * vec2(size));
  p.y = size.y - 1 - p.y;
  outColor = vec4(texelFetch(uImage, clamp(p, ivec2(0), size - 1), 0).rgb, 1.0);
}`;

// What a view leaves uncovered (beyond the frame's edge where the viewpoint looks past it)
// filled from what it covers by push-pull, as the CPU reference's PremulImage::over_fill and
// cpsl-render-gpu's fill.wgsl: pyramid levels hold colour weighted by alpha (rgb) and the
// weight (a). PUSH makes level l from level l - 1 (each pixel sums its 2x2 block, the weight
// clamped to 1); PULL fills level l from its pushed values and the filled level l + 1 (the
// pushed top, normalised, where uTop), sampled bilinearly at the pixel's centre.
const PUSH = `#version 300 es
precision highp float;
uniform highp sampler2D uFine;
out vec4 outColor;
void main() {
  ivec2 size = textureSize(uFine, 0);
  ivec2 p = ivec2(gl_FragCoord.xy) * 2;
  vec4 sum = vec4(0.0);
  for (int dy = 0; dy < 2; dy++)
    for (int dx = 0; dx < 2; dx++) {
      ivec2 q = p + ivec2(dx, dy);
      if (q.x < size.x && q.y < size.y) sum += texelFetch(uFine, q, 0);
    }
  outColor = sum.a > 1.0 ? sum / sum.a : sum;
}`;
const PULL = `#version 300 es
precision highp float;
uniform highp sampler2D uFine;
uniform highp sampler2D uCoarse;
uniform bool uTop;
out vec4 outColor;
vec3 filled(ivec2 q) {
  vec4 c = texelFetch(uCoarse, q, 0);
  if (uTop) return c.a > 0.0 ? c.rgb / c.a : vec3(0.0);
  return c.rgb;
}
vec3 taps(int i, int n) {
  float s = clamp((float(i) + 0.5) / 2.0 - 0.5, 0.0, float(n - 1));
  float i0 = floor(s);
  return vec3(i0, min(i0 + 1.0, float(n - 1)), s - i0);
}
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);
  ivec2 n = textureSize(uCoarse, 0);
  vec3 tx = taps(p.x, n.x), ty = taps(p.y, n.y);
  int x0 = int(tx.x), x1 = int(tx.y), y0 = int(ty.x), y1 = int(ty.y);
  vec3 up = mix(mix(filled(ivec2(x0, y0)), filled(ivec2(x1, y0)), tx.z),
                mix(filled(ivec2(x0, y1)), filled(ivec2(x1, y1)), tx.z), ty.z);
  vec4 own = texelFetch(uFine, p, 0);
  outColor = vec4(own.rgb + (1.0 - own.a) * up, 1.0);
}`;

// Mesh layers: each pixel's nearest triangle into a map; the composite applies that
// triangle's homography, exactly as for a plane.
const MESH_VERT = `#version 300 es
in vec4 aClip;
in float aTri;
flat out float vTri;
void main() {
  vTri = aTri;
  gl_Position = aClip;
}`;
const MESH_FRAG = `#version 300 es
precision highp float;
flat in float vTri;
out vec4 outColor;
void main() {
  outColor = vec4(vTri, 0.0, 1.0, 0.0);
}`;

function compile(gl: WebGL2RenderingContext, frag: string, vert = VERT): WebGLProgram {
  const shader = (type: number, src: string) => {
    const s = gl.createShader(type)!;
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
    return s;
  };
  const p = gl.createProgram()!;
  gl.attachShader(p, shader(gl.VERTEX_SHADER, vert));
  gl.attachShader(p, shader(gl.FRAGMENT_SHADER, frag));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
  return p;
}

interface Target {
  tex: WebGLTexture;
  fb: WebGLFramebuffer;
  width: number;
  height: number;
}

function target(gl: WebGL2RenderingContext, format: number, width: number, height: number): Target {
  const tex = gl.createTexture()!;
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, format, width, height);
  for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  const fb = gl.createFramebuffer()!;
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  return { tex, fb, width, height };
}

export class Renderer {
  readonly gl: WebGL2RenderingContext;
  private camera: Camera;
  private half: number;
  private composite: WebGLProgram;
  private dps: WebGLProgram;
  private present: WebGLProgram;
  private mesh: WebGLProgram;
  private maps: { tex: WebGLTexture; fb: WebGLFramebuffer; depth: WebGLRenderbuffer; slices: number } | null = null;
  private meshBuffer: WebGLBuffer;
  private triH: { tex: WebGLTexture; rows: number } | null = null;
  private planes: WebGLTexture[] = [];
  private streams = 0;
  private offsets: WebGLTexture;
  private targets: Target[];
  private push: WebGLProgram | null = null;
  private pull: WebGLProgram | null = null;
  /** Fill pyramid levels 1..n pushed, 1..n-1 pulled, and the filled view. */
  private pushed: Target[] = [];
  private pulled: Target[] = [];
  private filled: Target | null = null;
  private scratch = new Uint8Array(0);
  private frame: SideFrame | null = null;
  private scales: number[] = [];
  /** Strip half-width of the last render. */
  stripWidth = 0;
  /** Whether the Dynamic Pixel Strip runs. */
  dpsEnabled = true;
  /** Whether what the layers leave uncovered is filled (else shown black). */
  fillEnabled = true;
  /** Whether layers are resampled with the Catmull-Rom kernel (else bilinear). */
  cubic = false;

  constructor(canvas: HTMLCanvasElement, camera: Camera, codedHeight: number) {
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, preserveDrawingBuffer: true });
    if (!gl) throw new Error("this browser has no WebGL2");
    this.gl = gl;
    this.camera = camera;
    this.half = codedHeight;
    this.composite = compile(gl, COMPOSITE);
    this.dps = compile(gl, DPS);
    this.present = compile(gl, PRESENT);
    this.mesh = compile(gl, MESH_FRAG, MESH_VERT);
    this.meshBuffer = gl.createBuffer()!;
    this.offsets = gl.createTexture()!;
    gl.bindTexture(gl.TEXTURE_2D, this.offsets);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RG32F, MAX_LAYERS, MAX_LAYERS);
    this.targets = [0, 1].map(() => target(gl, gl.RGBA8, camera.width, camera.height));
    // The fill renders into float levels (EXT_color_buffer_float); without it the player
    // shows black where the layers leave the view uncovered.
    if (gl.getExtension("EXT_color_buffer_float")) {
      this.push = compile(gl, PUSH);
      this.pull = compile(gl, PULL);
      const levels: Target[] = [];
      let [w, h] = [camera.width, camera.height];
      // Halved (rounding up) until 1x1, at least once, as the CPU's pyramid.
      while (w > 1 || h > 1 || !levels.length) {
        [w, h] = [Math.ceil(w / 2), Math.ceil(h / 2)];
        levels.push(target(gl, gl.RGBA32F, w, h));
      }
      this.pushed = levels;
      this.pulled = levels.slice(0, -1).map((l) => target(gl, gl.RGBA32F, l.width, l.height));
      this.filled = target(gl, gl.RGBA8, camera.width, camera.height);
    }
  }

  /** Fills what `view` leaves uncovered into `this.filled`, level by level. */
  private fill(view: Target) {
    const gl = this.gl;
    if (!this.filled || !this.fillEnabled) return;
    const pass = (p: WebGLProgram, dst: Target, fine: Target, coarse: Target | null, top = false) => {
      gl.bindFramebuffer(gl.FRAMEBUFFER, dst.fb);
      gl.viewport(0, 0, dst.width, dst.height);
      gl.useProgram(p);
      gl.activeTexture(gl.TEXTURE3);
      gl.bindTexture(gl.TEXTURE_2D, fine.tex);
      gl.uniform1i(gl.getUniformLocation(p, "uFine"), 3);
      if (coarse) {
        gl.activeTexture(gl.TEXTURE4);
        gl.bindTexture(gl.TEXTURE_2D, coarse.tex);
        gl.uniform1i(gl.getUniformLocation(p, "uCoarse"), 4);
        gl.uniform1i(gl.getUniformLocation(p, "uTop"), top ? 1 : 0);
      }
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    };
    const n = this.pushed.length;
    const pushed = (l: number) => (l === 0 ? view : this.pushed[l - 1]);
    for (let l = 1; l <= n; l++) pass(this.push!, this.pushed[l - 1], pushed(l - 1), null);
    for (let l = n - 1; l >= 0; l--) {
      const coarse = l + 1 === n ? this.pushed[n - 1] : this.pulled[l];
      pass(this.pull!, l === 0 ? this.filled : this.pulled[l - 1], pushed(l), coarse, l + 1 === n);
    }
    gl.viewport(0, 0, this.camera.width, this.camera.height);
  }

  private ensurePlanes(streams: number, w: number, h: number) {
    const gl = this.gl;
    if (this.streams === streams && this.planes.length) return;
    for (const t of this.planes) gl.deleteTexture(t);
    this.planes = [
      [w, h],
      [w / 2, h / 2],
      [w / 2, h / 2],
    ].map(([pw, ph]) => {
      const t = gl.createTexture()!;
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
      gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.R8, pw, ph, streams);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
      return t;
    });
    this.streams = streams;
  }

  /** Uploads the decoded pictures of one frame (`frames[k]` is stream k, coded at downscale
   * `scales[k]`) and its side data. */
  async upload(frames: VideoFrame[], side: SideFrame, scales: number[]) {
    const gl = this.gl;
    // The planes hold full-size pictures; a downscaled stream fills their top-left corner.
    this.ensurePlanes(frames.length, this.camera.width + (this.camera.width & 1), 2 * this.half);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    for (const [s, f] of frames.entries()) {
      const w = f.visibleRect?.width ?? f.codedWidth;
      const h = f.visibleRect?.height ?? f.codedHeight;
      // Software decoders give I420; hardware ones may give NV12 (chroma interleaved).
      if (f.format !== "I420" && f.format !== "I420A" && f.format !== "NV12")
        throw new Error(`unsupported picture format ${f.format}`);
      const nv12 = f.format === "NV12";
      const size = f.allocationSize();
      if (this.scratch.length < size) this.scratch = new Uint8Array(size);
      const layout = await f.copyTo(this.scratch);
      const dims = [
        [w, h],
        [w / 2, h / 2],
        [w / 2, h / 2],
      ];
      for (let p = 0; p < 3; p++) {
        gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.planes[p]);
        if (nv12 && p > 0) {
          // Split the interleaved chroma plane.
          const l = layout[1];
          const [pw, ph] = dims[p];
          const out = new Uint8Array(pw * ph);
          for (let y = 0; y < ph; y++)
            for (let x = 0; x < pw; x++) out[y * pw + x] = this.scratch[l.offset + y * l.stride + 2 * x + (p - 1)];
          gl.pixelStorei(gl.UNPACK_ROW_LENGTH, 0);
          gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, s, pw, ph, 1, gl.RED, gl.UNSIGNED_BYTE, out);
          continue;
        }
        const l = layout[p];
        gl.pixelStorei(gl.UNPACK_ROW_LENGTH, l.stride);
        gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, s, dims[p][0], dims[p][1], 1, gl.RED, gl.UNSIGNED_BYTE, this.scratch, l.offset);
      }
    }
    gl.pixelStorei(gl.UNPACK_ROW_LENGTH, 0);
    const off = new Float32Array(MAX_LAYERS * MAX_LAYERS * 2);
    for (const [key, [fo, bo]] of side.offsets) {
      const [f, b] = [key >> 8, key & 255];
      if (f < MAX_LAYERS && b < MAX_LAYERS) off.set([fo, bo], (b * MAX_LAYERS + f) * 2);
    }
    gl.bindTexture(gl.TEXTURE_2D, this.offsets);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, MAX_LAYERS, MAX_LAYERS, gl.RG, gl.FLOAT, off);
    this.frame = side;
    this.scales = scales;
  }

  private bindLayers(p: WebGLProgram, pose: Pose) {
    const gl = this.gl;
    const side = this.frame!;
    const cam = this.camera;
    const hs = new Float32Array(MAX_LAYERS * 9);
    const planes = new Float32Array(MAX_LAYERS * 4);
    const mesh = new Int32Array(MAX_LAYERS).fill(-1);
    let slice = 0;
    const streams = new Int32Array(MAX_LAYERS);
    const scales = new Int32Array(MAX_LAYERS);
    let n = 0;
    for (const l of side.layers.slice(0, MAX_LAYERS)) {
      const h = layerInverse(cam, cam, pose, l.depth, l.geometry);
      planes.set(horizonClip(cam, l.geometry), n * 4);
      if (l.geometry.kind === "mesh") mesh[n] = slice++;
      // A layer the viewer has passed is skipped, as the CPU renderer does.
      const m = h ?? [
        [0, 0, 0],
        [0, 0, 0],
        [0, 0, -1],
      ];
      // Column-major for GLSL.
      for (let c = 0; c < 3; c++) for (let r = 0; r < 3; r++) hs[n * 9 + c * 3 + r] = m[r][c];
      streams[n] = l.stream;
      scales[n] = this.scales[l.stream] ?? 1;
      n++;
    }
    gl.useProgram(p);
    const u = (name: string) => gl.getUniformLocation(p, name);
    gl.uniformMatrix3fv(u("uH"), false, hs);
    gl.uniform4fv(u("uPlane"), planes);
    gl.uniform1iv(u("uMesh"), mesh);
    // Units of their own even without meshes: samplers of different types may not share one.
    gl.uniform1i(u("uMaps"), 5);
    gl.uniform1i(u("uTriH"), 6);
    if (this.maps && this.triH) {
      gl.activeTexture(gl.TEXTURE5);
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.maps.tex);
      gl.activeTexture(gl.TEXTURE6);
      gl.bindTexture(gl.TEXTURE_2D, this.triH.tex);
    }
    gl.uniform1iv(u("uStream"), streams);
    gl.uniform1iv(u("uScale"), scales);
    gl.uniform1i(u("uLayers"), n);
    gl.uniform1i(u("uCubic"), this.cubic ? 1 : 0);
    gl.uniform2i(u("uSize"), cam.width, cam.height);
    gl.uniform1i(u("uHalf"), this.half);
    this.planes.forEach((t, i) => {
      gl.activeTexture(gl.TEXTURE0 + i);
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
      gl.uniform1i(u(["uY", "uU", "uV"][i]), i);
    });
  }

  /** Source maps of the frame's mesh layers for `pose` (one array slice each). */
  private drawMeshes(pose: Pose) {
    const gl = this.gl;
    const cam = this.camera;
    const meshes = this.frame!.layers.slice(0, MAX_LAYERS).flatMap((l) => (l.geometry.kind === "mesh" ? [l.geometry.grid] : []));
    if (!meshes.length) return;
    if (!this.maps || this.maps.slices < meshes.length) {
      if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("mesh layers need WebGL2's EXT_color_buffer_float");
      if (this.maps) {
        gl.deleteTexture(this.maps.tex);
        gl.deleteFramebuffer(this.maps.fb);
        gl.deleteRenderbuffer(this.maps.depth);
      }
      const tex = gl.createTexture()!;
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, tex);
      gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA32F, cam.width, cam.height, meshes.length);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
      const depth = gl.createRenderbuffer()!;
      gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, cam.width, cam.height);
      this.maps = { tex, fb: gl.createFramebuffer()!, depth, slices: meshes.length };
    }
    const maps = this.maps;
    // Every mesh layer's triangles, numbered across the layers; their homographies in uTriH.
    let count = 0;
    const parts = meshes.map((grid) => {
      const t = meshTriangles(cam, grid, pose, count);
      count += t.h.length / 12;
      return t;
    });
    const rows = Math.max(1, Math.ceil(count / TRIS_PER_ROW));
    if (!this.triH || this.triH.rows < rows) {
      if (this.triH) gl.deleteTexture(this.triH.tex);
      const tex = gl.createTexture()!;
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, 3 * TRIS_PER_ROW, rows);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      this.triH = { tex, rows };
    }
    const all = new Float32Array(rows * TRIS_PER_ROW * 12);
    let at = 0;
    for (const t of parts) {
      all.set(t.h, at);
      at += t.h.length;
    }
    gl.bindTexture(gl.TEXTURE_2D, this.triH.tex);
    gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, 3 * TRIS_PER_ROW, rows, gl.RGBA, gl.FLOAT, all);
    gl.bindFramebuffer(gl.FRAMEBUFFER, maps.fb);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, maps.depth);
    gl.useProgram(this.mesh);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.meshBuffer);
    const clip = gl.getAttribLocation(this.mesh, "aClip");
    const tri = gl.getAttribLocation(this.mesh, "aTri");
    gl.enableVertexAttribArray(clip);
    gl.enableVertexAttribArray(tri);
    gl.vertexAttribPointer(clip, 4, gl.FLOAT, false, 20, 0);
    gl.vertexAttribPointer(tri, 1, gl.FLOAT, false, 20, 16);
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    for (const [i, t] of parts.entries()) {
      gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, maps.tex, 0, i);
      gl.clearColor(0, 0, 0, 0);
      gl.clearDepth(1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      gl.bufferData(gl.ARRAY_BUFFER, t.clip, gl.STREAM_DRAW);
      gl.drawArrays(gl.TRIANGLES, 0, t.clip.length / 5);
    }
    gl.disable(gl.DEPTH_TEST);
    gl.disableVertexAttribArray(clip);
    gl.disableVertexAttribArray(tri);
  }

  /** Renders the uploaded frame from `pose`; the result stays in an offscreen target. */
  render(pose: Pose) {
    if (!this.frame) return;
    const gl = this.gl;
    const cam = this.camera;
    gl.viewport(0, 0, cam.width, cam.height);
    this.drawMeshes(pose);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.targets[0].fb);
    this.bindLayers(this.composite, pose);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    this.result = this.targets[0];
    if (!this.dpsEnabled) return this.fill(this.result);
    const depths = this.frame.layers.map((l) => l.depth);
    this.stripWidth = stripWidth(cam, pose, depths);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.targets[1].fb);
    this.bindLayers(this.dps, pose);
    const u = (name: string) => gl.getUniformLocation(this.dps, name);
    gl.activeTexture(gl.TEXTURE3);
    gl.bindTexture(gl.TEXTURE_2D, this.targets[0].tex);
    gl.uniform1i(u("uImage"), 3);
    gl.activeTexture(gl.TEXTURE4);
    gl.bindTexture(gl.TEXTURE_2D, this.offsets);
    gl.uniform1i(u("uOffsets"), 4);
    const logs = new Float32Array(MAX_LAYERS);
    depths.slice(0, MAX_LAYERS).forEach((d, i) => (logs[i] = Math.log(d)));
    gl.uniform1fv(u("uLogDepth"), logs);
    gl.uniform1i(u("uReach"), 2 * this.stripWidth);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    this.result = this.targets[1];
    this.fill(this.result);
  }

  private result: Target | null = null;

  /** Draws the last render, what it leaves uncovered filled, into the canvas rectangle
   * `x, y, w, h` (GL coordinates). */
  show(x: number, y: number, w: number, h: number) {
    if (!this.result) return;
    const gl = this.gl;
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(x, y, w, h);
    gl.useProgram(this.present);
    gl.activeTexture(gl.TEXTURE3);
    gl.bindTexture(gl.TEXTURE_2D, ((this.fillEnabled && this.filled) || this.result).tex);
    gl.uniform1i(gl.getUniformLocation(this.present, "uImage"), 3);
    gl.uniform2i(gl.getUniformLocation(this.present, "uView"), x, y);
    gl.uniform2i(gl.getUniformLocation(this.present, "uViewSize"), w, h);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /** The last render as premultiplied RGBA rows, top row first (for tests and snapshots). */
  pixels(): Uint8Array {
    const gl = this.gl;
    const { width: w, height: h } = this.camera;
    const out = new Uint8Array(w * h * 4);
    if (!this.result) return out;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.result.fb);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, out);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return out;
  }
}

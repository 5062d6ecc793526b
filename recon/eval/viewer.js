// recon's 3D viewer: a run's Gaussians (or its mesh), the sfm points and the camera frusta in
// WebGL2, written for recon (no dependencies, works from file:// and from a web server).
//
// The splats are drawn as recon's CPU rasterizer draws them (Kerbl et al. 2023, Sec. 4 and 6):
// EWA projection with the 0.3 px dilation and the 1.3x frustum guard band, the 3-sigma radius
// widened to whole 16 or 32 px tiles, alpha = min(0.99, o exp(power)) dropped below 1/255,
// SH colour + 0.5 clamped at 0, antialiased runs with the sqrt(det ratio) compensation
// (Yu et al. 2024, eq. 12), blended back to front over the background in a float target.
// The scene arrives as `window.RECON_VIEWS[name]` from a script file beside the page.
"use strict";

(function () {
  const TILE = 16, TILE_LARGE = 32, LARGE_IMAGE = 384 * 384;
  const DILATION = 0.3, GUARD_BAND = 1.3;
  const TEX_WIDTH = 2048;
  const DISPLAY_WIDTH = 640;  // px: the width a camera's view is drawn at in the page
  const PICK_RADIUS = 12;  // px: how near a click must be to a camera's centre to fly there
  // While the view moves, each frame is drawn within FRAME_BUDGET_MS (20 frames a second) at
  // a level of detail set from the last frame's time (`nextLod`): first a coarser resolution,
  // bilinearly upsampled (the splats' fragments go as its square), down to MIN_SCALE, then
  // only the most prominent Gaussians (opacity x cube root of the covariance's determinant),
  // down to MIN_SHARE of them; SETTLE_MS after the last move the view is drawn in full.
  const FRAME_BUDGET_MS = 50, MIN_SCALE = 0.25, MIN_SHARE = 0.05, SETTLE_MS = 250;

  // recon's packed layout (`recon.gaussians.splat_pack`, ~16 bytes a Gaussian): gzip of the
  // chunks' float bounds (the compressed PLY's, per 256 Gaussians in Morton order), then byte
  // planes per Gaussian: position 11-10-11 bit fractions of its chunk's box, rotation "smallest
  // three" at 7-7-8 bits under a 2-bit index, log-scale and DC colour 8-bit fractions of the
  // chunk's ranges, opacity 8 bits, the index of its SH bands in a k-means codebook; then the
  // codebook as 8-bit fractions of each coefficient's range -> the float arrays the exact path
  // carries.
  const SH_C0 = 0.28209479177387814;
  const ROTATION_BITS = [7, 7, 8];

  // R diag(s) (R diag(s))^T, upper triangle (xx xy xz yy yz zz), of a unit quaternion wxyz
  function covariance(q, scale) {
    const [w, x, y, z] = q;
    const R = [
      1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
      2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
      2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ];
    const M = (row, col) => R[3 * row + col] * scale[col];
    const S = (a, b) => M(a, 0) * M(b, 0) + M(a, 1) * M(b, 1) + M(a, 2) * M(b, 2);
    return [S(0, 0), S(0, 1), S(0, 2), S(1, 1), S(1, 2), S(2, 2)];
  }

  function unpack(s, raw) {
    const n = s.count, k = s.sh_bases, D = 3 * (k - 1);
    const section = (name) => {
      const [offset, length] = s.sections[name];
      return raw.subarray(offset, offset + length);
    };
    const floats = (name) => new Float32Array(section(name).slice().buffer);
    const chunks = floats("chunks");
    const pos = section("position"), rot = section("rotation");
    const scl = section("scale"), col = section("colour");
    const labels = k > 1 ? section("sh_labels") : null, book = k > 1 ? section("sh_codebook") : null;
    const range = k > 1 ? floats("sh_range") : null;
    const means = new Float32Array(3 * n), cov = new Float32Array(6 * n);
    const opacity = new Float32Array(n), sh = new Float32Array(3 * k * n);
    const [b0, b1, b2] = ROTATION_BITS;
    const top = ROTATION_BITS.map((b) => (1 << b) - 1);
    for (let i = 0; i < n; i++) {
      const c = chunks.subarray(18 * (i >> 8), 18 * (i >> 8) + 18);
      const lerp = (lo, hi, t) => c[lo] * (1 - t) + c[hi] * t;
      const p = (pos[i] | (pos[n + i] << 8) | (pos[2 * n + i] << 16) | (pos[3 * n + i] << 24)) >>> 0;
      const tp = [(p >>> 21) / 2047, ((p >>> 11) & 1023) / 1023, (p & 2047) / 2047];
      for (let a = 0; a < 3; a++) means[3 * i + a] = lerp(a, 3 + a, tp[a]);
      const scale = [0, 1, 2].map((a) => Math.exp(lerp(6 + a, 9 + a, scl[a * n + i] / 255)));
      const r = rot[i] | (rot[n + i] << 8) | (rot[2 * n + i] << 16);
      const three = [(r >>> (b1 + b2)) & top[0], (r >>> b2) & top[1], r & top[2]].map(
        (v, j) => (v / top[j] - 0.5) * Math.SQRT2);
      const largest = r >>> (b0 + b1 + b2), q = [0, 0, 0, 0];
      q[largest] = Math.sqrt(Math.max(0, 1 - three[0] ** 2 - three[1] ** 2 - three[2] ** 2));
      for (let a = 0, j = 0; a < 4; a++) if (a !== largest) q[a] = three[j++];
      cov.set(covariance(q, scale), 6 * i);
      opacity[i] = col[3 * n + i] / 255;
      for (let a = 0; a < 3; a++)
        sh[3 * k * i + a] = (lerp(12 + a, 15 + a, col[a * n + i] / 255) - 0.5) / SH_C0;
      if (k > 1) {
        const entry = (labels[i] | (labels[n + i] << 8)) * D;
        for (let d = 0; d < D; d++)  // coefficient d = 3 (band - 1) + channel
          sh[3 * k * i + 3 + d] = range[d] + (book[entry + d] / 255) * (range[D + d] - range[d]);
      }
    }
    return { means, cov, opacity, sh, intervals: null };
  }

  // The packed bytes: a string of the scene script, read with charset="x-user-defined" (every
  // byte one character, 0x80-0xFF as U+F780-U+F7FF); a server that forces another charset
  // garbles it, and then the script itself is fetched and its string read byte by byte.
  async function packedBytes(s, src) {
    const text = s.bytes || "";
    if (text.length === s.bytes_length) {
      const out = new Uint8Array(text.length);
      for (let i = 0; i < text.length; i++) out[i] = text.charCodeAt(i) & 255;
      return out;
    }
    if (!/^https?:$/.test(location.protocol) || !src)
      throw new Error("the scene's packed Gaussians did not load intact (open the page with recon view)");
    const file = new Uint8Array(await (await fetch(src)).arrayBuffer());
    const marker = new TextEncoder().encode('.bytes = "');
    let i = 0;
    search: for (; i <= file.length - marker.length; i++) {
      for (let j = 0; j < marker.length; j++) if (file[i + j] !== marker[j]) continue search;
      break;
    }
    const out = new Uint8Array(s.bytes_length), escaped = { 110: 10, 114: 13, 34: 34, 92: 92 };
    let n = 0;
    for (i += marker.length; i < file.length && file[i] !== 34; i++)
      out[n++] = file[i] === 92 ? escaped[file[++i]] : file[i];
    if (n !== s.bytes_length) throw new Error("the scene's packed Gaussians are damaged");
    return out;
  }

  // The next moving frame's level of detail {scale, share} from the last one's `ms`: over the
  // budget, a coarser resolution first, then fewer Gaussians; well under it (1.5x), the
  // Gaussians back first, then the resolution. Example: {1, 1} at 800 ms -> scale 0.24 ->
  // clamped 0.25; {0.25, 1} at 100 ms -> share 0.475; {0.25, 0.5} at 20 ms -> share 1.
  function nextLod(lod, ms, budget = FRAME_BUDGET_MS) {
    let { scale, share } = lod;
    const r = budget / Math.max(ms, 1e-3);
    if (r < 1) {
      if (scale > MIN_SCALE) scale = Math.max(MIN_SCALE, scale * Math.sqrt(r) * 0.95);
      else share = Math.max(MIN_SHARE, share * r * 0.95);
    } else if (r > 1.5) {
      const up = Math.min(r / 1.2, 2);
      if (share < 1) share = Math.min(1, share * up);
      else scale = Math.min(1, scale * Math.sqrt(up));
    }
    return { scale, share };
  }
  // the first moving frame's level of detail, from a full frame's `ms`: nextLod applied to the
  // times it predicts (fragments ~ scale^2, the rest ~ share)
  function lodFor(ms, budget = FRAME_BUDGET_MS) {
    let lod = { scale: 1, share: 1 };
    for (let k = 0; k < 8; k++) {
      const next = nextLod(lod, ms, budget);
      if (next.scale === lod.scale && next.share === lod.share) break;
      ms *= (next.scale / lod.scale) ** 2 * (next.share / lod.share);
      lod = next;
    }
    return lod;
  }

  async function gunzip(bytes) {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  }

  function decode(b64, Type) {
    const bin = atob(b64);
    const bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Type(bytes.buffer);
  }

  // ---- small linear algebra on row-major 4x4 arrays ------------------------------------------
  function matmul(a, b) {
    const o = new Float64Array(16);
    for (let i = 0; i < 4; i++)
      for (let j = 0; j < 4; j++) {
        let s = 0;
        for (let k = 0; k < 4; k++) s += a[4 * i + k] * b[4 * k + j];
        o[4 * i + j] = s;
      }
    return o;
  }
  function rigidInverse(m) { // [R t; 0 1]^-1 = [R^T -R^T t; 0 1]
    const o = new Float64Array(16);
    for (let i = 0; i < 3; i++) {
      for (let j = 0; j < 3; j++) o[4 * i + j] = m[4 * j + i];
      o[4 * i + 3] = -(m[i] * m[3] + m[4 + i] * m[7] + m[8 + i] * m[11]);
    }
    o[15] = 1;
    return o;
  }
  function rotation(axis, angle) { // Rodrigues, as a row-major 4x4
    const [x, y, z] = axis, c = Math.cos(angle), s = Math.sin(angle), t = 1 - c;
    return new Float64Array([
      t * x * x + c, t * x * y - s * z, t * x * z + s * y, 0,
      t * x * y + s * z, t * y * y + c, t * y * z - s * x, 0,
      t * x * z - s * y, t * y * z + s * x, t * z * z + c, 0,
      0, 0, 0, 1,
    ]);
  }
  function translation(v) {
    return new Float64Array([1, 0, 0, v[0], 0, 1, 0, v[1], 0, 0, 1, v[2], 0, 0, 0, 1]);
  }
  function normalize(v) {
    const n = Math.hypot(v[0], v[1], v[2]) || 1;
    return [v[0] / n, v[1] / n, v[2] / n];
  }

  // ---- WebGL helpers -------------------------------------------------------------------------
  function program(gl, vs, fs) {
    const p = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, src);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      gl.attachShader(p, s);
    }
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    return p;
  }
  function floatTexture(gl, texels, data) { // RGBA32F, TEX_WIDTH texels a row
    const rows = Math.max(1, Math.ceil(texels / TEX_WIDTH));
    const padded = new Float32Array(rows * TEX_WIDTH * 4);
    padded.set(data);
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, TEX_WIDTH, rows, 0, gl.RGBA, gl.FLOAT, padded);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
      gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    return t;
  }

  const SPLAT_VS = `#version 300 es
precision highp float; precision highp int;
uniform highp sampler2D uGeom;   // 3 texels a splat: mean.xyz opacity | cov xx xy xz yy |
                                 // cov yz zz, finest training sampling interval
uniform highp sampler2D uSh;     // 16 texels a splat: SH coefficient k as rgb
uniform mat4 uView;              // cam_from_world (OpenCV: x right, y down, z forward)
uniform vec4 uIntr;              // fx fy cx cy (px)
uniform vec2 uSize;              // width height (px)
uniform vec3 uCenter;            // camera centre (world)
uniform int uDegree, uTile, uAntialiased, uFootprint;
uniform float uNear;
uniform highp usampler2D uOrder;  // the splats back to front, one a texel
out vec3 vColor; out vec3 vConic; out vec2 vMean; out float vOpacity; flat out vec4 vBox;
ivec2 texel(int i) { return ivec2(i % ${TEX_WIDTH}, i / ${TEX_WIDTH}); }
vec3 sh(int base, int k) { return texelFetch(uSh, texel(base + k), 0).rgb; }
void main() {
  // vertex 4 s + k is corner k of the s-th splat from the back (drawn as two indexed
  // triangles: one draw, no instancing, which a software WebGL pays for per instance)
  int i = int(texelFetch(uOrder, texel(gl_VertexID >> 2), 0).r);
  vec4 g0 = texelFetch(uGeom, texel(3 * i), 0);
  vec4 g1 = texelFetch(uGeom, texel(3 * i + 1), 0);
  vec4 g2 = texelFetch(uGeom, texel(3 * i + 2), 0);
  gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // culled unless drawn below
  vec3 p = (uView * vec4(g0.xyz, 1.0)).xyz;
  if (p.z <= uNear) return;
  mat3 S = mat3(g1.x, g1.y, g1.z, g1.y, g1.w, g2.x, g1.z, g2.x, g2.y);
  mat3 W = mat3(uView);
  mat3 Sc = W * S * transpose(W);
  float fx = uIntr.x, fy = uIntr.y, cx = uIntr.z, cy = uIntr.w;
  float mx = (GUARD_BAND_M1) * uSize.x / (2.0 * fx), my = (GUARD_BAND_M1) * uSize.y / (2.0 * fy);
  float u = clamp(p.x / p.z, -cx / fx - mx, (uSize.x - cx) / fx + mx);
  float v = clamp(p.y / p.z, -cy / fy - my, (uSize.y - cy) / fy + my);
  vec3 j0 = (fx / p.z) * vec3(1.0, 0.0, -u), j1 = (fy / p.z) * vec3(0.0, 1.0, -v);
  // the 0.3 px^2 dilation, held in world units where this view is finer than the training
  // views were (the footprint filter: 0.3 max(1, (f T / z)^2))
  float ratio = fx * g2.z / p.z;
  float dil = uFootprint == 1 ? ${DILATION} * max(1.0, ratio * ratio) : ${DILATION};
  float a = dot(j0, Sc * j0) + dil, b = dot(j0, Sc * j1), c = dot(j1, Sc * j1) + dil;
  float det = a * c - b * b;
  if (!(det > 0.0)) return;
  vec2 mean = vec2(fx * p.x / p.z + cx, fy * p.y / p.z + cy);
  float halfGap = max(length(vec2(0.5 * (a - c), b)), sqrt(0.1));
  float r = ceil(3.0 * sqrt(0.5 * (a + c) + halfGap));
  if (mean.x + r <= 0.0 || mean.x - r >= uSize.x || mean.y + r <= 0.0 || mean.y - r >= uSize.y) return;
  float opacity = g0.w;
  if (uAntialiased == 1) {
    float A = c / det, B = -b / det, C = a / det;
    float kept = 1.0 - dil * (A + C) + dil * dil * (A * C - B * B);  // det Sigma / det Sigma'
    opacity *= sqrt(clamp(kept, 1e-12, 1.0));
  }
  // the pixels of every tile the 3-sigma box touches (the rasterizer's candidates), within
  // the ellipse where alpha can reach 1/255 (d^T Sigma'^-1 d <= q = 2 ln(255 o)); outside it
  // every fragment would be discarded anyway. The quad drawn is the smaller of two that hold
  // those pixels: the ellipse's axis-aligned box (half sides sqrt(q a), sqrt(q c)) cut to the
  // tiles, or its box along its axes (half sides sqrt(q lambda)), the tiles then cut per
  // fragment (vBox): a long thin splat at 45 degrees covers a fraction of its aligned box
  if (opacity * 255.0 <= 1.0) return;
  vec2 grid = ceil(uSize / float(uTile));
  vec2 lo = min(max(floor((mean - r) / float(uTile)), 0.0), grid);
  vec2 hi = min(max(floor((mean + r) / float(uTile)), -1.0) + 1.0, grid);
  if (any(lessThanEqual(hi, lo))) return;
  float q = 2.0 * log(255.0 * opacity);
  vec2 reach = sqrt(q * vec2(a, c)) * 1.001 + 0.01;
  vec2 from = max(lo * float(uTile), mean - reach), to = min(hi * float(uTile), mean + reach);
  if (any(lessThanEqual(to, from))) return;
  vBox = vec4(lo, hi) * float(uTile);
  vec2 corner = vec2(gl_VertexID & 1, (gl_VertexID >> 1) & 1);
  vec2 pixel = mix(from, to, corner);
  float gap = length(vec2(0.5 * (a - c), b));  // eigenvalues 0.5 (a + c) +- gap
  vec2 axes = sqrt(q * max(0.5 * (a + c) + vec2(gap, -gap), 0.0)) * 1.001 + 0.01;
  if (4.0 * axes.x * axes.y < (to.x - from.x) * (to.y - from.y)) {
    vec2 major = abs(b) > 1e-9 * (a + c) ? normalize(vec2(b, 0.5 * (c - a) + gap))
                                         : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 side = 2.0 * corner - 1.0;
    pixel = mean + side.x * axes.x * major + side.y * axes.y * vec2(-major.y, major.x);
  }
  gl_Position = vec4(2.0 * pixel.x / uSize.x - 1.0, 1.0 - 2.0 * pixel.y / uSize.y, 0.0, 1.0);
  // colour: SH up to uDegree at the direction from the camera centre, + 0.5, >= 0
  vec3 d = normalize(g0.xyz - uCenter);
  float x = d.x, y = d.y, z = d.z;
  int base = 16 * i;
  vec3 col = 0.28209479177387814 * sh(base, 0);
  if (uDegree >= 1)
    col += -0.4886025119029199 * y * sh(base, 1) + 0.4886025119029199 * z * sh(base, 2)
      - 0.4886025119029199 * x * sh(base, 3);
  if (uDegree >= 2) {
    float xx = x * x, yy = y * y, zz = z * z;
    col += 1.0925484305920792 * x * y * sh(base, 4) - 1.0925484305920792 * y * z * sh(base, 5)
      + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh(base, 6)
      - 1.0925484305920792 * x * z * sh(base, 7) + 0.5462742152960396 * (xx - yy) * sh(base, 8);
    if (uDegree >= 3)
      col += -0.5900435899266435 * y * (3.0 * xx - yy) * sh(base, 9)
        + 2.890611442640554 * x * y * z * sh(base, 10)
        - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh(base, 11)
        + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh(base, 12)
        - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh(base, 13)
        + 1.445305721320277 * z * (xx - yy) * sh(base, 14)
        - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh(base, 15);
  }
  vColor = max(col + 0.5, 0.0);
  vConic = vec3(c, -b, a) / det;
  vMean = mean;
  vOpacity = opacity;
}`.replace(/GUARD_BAND_M1/g, (GUARD_BAND - 1).toFixed(4));

  const SPLAT_FS = `#version 300 es
precision highp float;
uniform vec2 uSize;
in vec3 vColor; in vec3 vConic; in vec2 vMean; in float vOpacity; flat in vec4 vBox;
out vec4 outColor;
void main() {
  vec2 pixel = vec2(gl_FragCoord.x, uSize.y - gl_FragCoord.y);  // recon's (col + 0.5, row + 0.5)
  if (any(lessThan(pixel, vBox.xy)) || any(greaterThanEqual(pixel, vBox.zw))) discard;
  vec2 d = vMean - pixel;
  float power = -0.5 * (vConic.x * d.x * d.x + vConic.z * d.y * d.y) - vConic.y * d.x * d.y;
  float alpha = min(0.99, vOpacity * exp(power));
  if (power > 0.0 || alpha < 1.0 / 255.0) discard;
  outColor = vec4(vColor * alpha, alpha);  // premultiplied: drawn back to front with "over"
}`;

  const LINE_VS = `#version 300 es
precision highp float;
uniform mat4 uView; uniform vec4 uIntr; uniform vec2 uSize; uniform float uNear;
layout(location = 0) in vec3 aPos; layout(location = 1) in vec3 aColor; out vec3 vColor;
void main() {
  vec3 p = (uView * vec4(aPos, 1.0)).xyz;
  float z = max(p.z, uNear);
  vec2 px = vec2(uIntr.x * p.x / z + uIntr.z, uIntr.y * p.y / z + uIntr.w);
  gl_Position = vec4(2.0 * px.x / uSize.x - 1.0, 1.0 - 2.0 * px.y / uSize.y, 0.0, 1.0);
  if (p.z <= uNear) gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
  gl_PointSize = 2.0;
  vColor = aColor;
}`;
  const LINE_FS = `#version 300 es
precision highp float;
in vec3 vColor; out vec4 outColor;
void main() { outColor = vec4(vColor, 1.0); }`;

  const MESH_VS = `#version 300 es
precision highp float;
uniform mat4 uView; uniform vec4 uIntr; uniform vec2 uSize; uniform float uNear, uFar;
layout(location = 0) in vec3 aPos; layout(location = 1) in vec3 aColor; out vec3 vColor;
void main() {
  vec3 p = (uView * vec4(aPos, 1.0)).xyz;
  vec2 px = vec2(uIntr.x * p.x, uIntr.y * p.y) + vec2(uIntr.z, uIntr.w) * p.z;
  // perspective with depth: clip w = z, depth from near..far
  float zc = (p.z - uNear) / (uFar - uNear) * 2.0 - 1.0;
  gl_Position = vec4(2.0 * px.x / uSize.x - p.z, p.z - 2.0 * px.y / uSize.y, zc * p.z, p.z);
  vColor = aColor;
}`;

  const BLIT_VS = `#version 300 es
out vec2 vUv;
void main() {
  vec2 c = vec2(gl_VertexID & 1, gl_VertexID >> 1);
  vUv = c;
  gl_Position = vec4(2.0 * c - 1.0, 0.0, 1.0);
}`;
  // the drawn region (uRegion px of the target, from its corner) bilinearly resampled to the
  // canvas: the same pixels where the two are the same size
  const BLIT_FS = `#version 300 es
precision highp float;
uniform highp sampler2D uImage; uniform vec2 uRegion; in vec2 vUv; out vec4 outColor;
vec3 at(ivec2 p) {
  return texelFetch(uImage, clamp(p, ivec2(0), ivec2(uRegion) - 1), 0).rgb;
}
void main() {
  vec2 p = vUv * uRegion - 0.5, f = fract(p);
  ivec2 i = ivec2(floor(p));
  vec3 c = mix(mix(at(i), at(i + ivec2(1, 0)), f.x), mix(at(i + ivec2(0, 1)), at(i + 1), f.x), f.y);
  outColor = vec4(clamp(c, 0.0, 1.0), 1.0);
}`;

  // ---- the viewer --------------------------------------------------------------------------
  class Viewer {
    constructor(root, scene) {
      this.root = root;
      this.scene = scene;
      this.canvas = root.querySelector("canvas");
      const gl = (this.gl = this.canvas.getContext("webgl2", {
        antialias: false, preserveDrawingBuffer: true, premultipliedAlpha: false,
      }));
      if (!gl) throw new Error("this browser has no WebGL2");
      if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("no float render targets");
      this.showCameras = true;
      this.showPoints = false;  // drawn over the splats (they write no depth): off at first
      this.programs = {
        splat: program(gl, SPLAT_VS, SPLAT_FS),
        line: program(gl, LINE_VS, LINE_FS),
        mesh: program(gl, MESH_VS, LINE_FS),
        blit: program(gl, BLIT_VS, BLIT_FS),
      };
      this.vao = gl.createVertexArray();
      this.emptyVao = gl.createVertexArray();
      this._loadSplats();
      this._loadLines();
      this._loadPoints();
      this._loadMesh();
      this.target = this._sceneCentre();
      this.up = this._sceneUp();
      this._controls();
      this.setCamera(this.scene.start || 0);
    }

    _sceneCentre() {
      const cams = this.scene.cameras;
      if (this.scene.centre) return this.scene.centre;
      const c = [0, 0, 0];
      for (const cam of cams) for (let k = 0; k < 3; k++) c[k] += cam.centre[k] / cams.length;
      return c;
    }
    _sceneUp() { // minus the cameras' mean y axis (OpenCV y points down in the image)
      const u = [0, 0, 0];
      for (const cam of this.scene.cameras) {
        const m = cam.cam_from_world;
        for (let k = 0; k < 3; k++) u[k] -= m[4 + k];
      }
      return normalize(u);
    }

    _loadSplats() {
      const s = this.scene.splats;
      this.count = s ? s.count : 0;
      if (!this.count) return;
      const gl = this.gl;
      if (s.encoding !== "pack" && s.encoding !== "float32")
        throw new Error(`a scene of another recon (${s.encoding}): run recon eval again`);
      const { means, cov, opacity, sh, intervals } = s.encoding === "pack" ? s.decoded : {
        means: decode(s.means, Float32Array),
        cov: decode(s.cov, Float32Array),
        opacity: decode(s.opacity, Float32Array),
        sh: decode(s.sh, Float32Array),
        intervals: s.intervals ? decode(s.intervals, Float32Array) : null,
      };
      const geom = new Float32Array(this.count * 12);
      for (let i = 0; i < this.count; i++) {
        geom.set([means[3 * i], means[3 * i + 1], means[3 * i + 2], opacity[i]], 12 * i);
        geom.set(cov.subarray(6 * i, 6 * i + 6), 12 * i + 4);
        if (intervals) geom[12 * i + 10] = intervals[i];
      }
      const k = s.sh_bases;
      const shTex = new Float32Array(this.count * 16 * 4);
      for (let i = 0; i < this.count; i++)
        for (let j = 0; j < k; j++)
          for (let ch = 0; ch < 3; ch++) shTex[4 * (16 * i + j) + ch] = sh[3 * (k * i + j) + ch];
      this.means = means;
      this.intervals = intervals;
      this.trace = new Float32Array(this.count);  // of Sigma: its largest eigenvalue at most
      for (let i = 0; i < this.count; i++) this.trace[i] = cov[6 * i] + cov[6 * i + 3] + cov[6 * i + 5];
      this.opacity = opacity;
      this.all = new Uint32Array(this.count).map((_, i) => i);
      // most prominent first (a moving view's level of detail draws a prefix): opacity x the
      // cube root of det Sigma (the Gaussian's mean area, up to a constant)
      const prominence = new Float32Array(this.count);
      for (let i = 0; i < this.count; i++) {
        const [xx, xy, xz, yy, yz, zz] = cov.subarray(6 * i, 6 * i + 6);
        const det = xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz);
        prominence[i] = opacity[i] * Math.cbrt(Math.max(det, 0));
      }
      this.prominent = this.all.slice().sort((i, j) => prominence[j] - prominence[i]);
      this.geomTex = floatTexture(gl, 3 * this.count, geom);
      this.shTex = floatTexture(gl, 16 * this.count, shTex);
      // the order, a texel a splat, rewritten every frame; the quads' corners, indexed once
      const rows = Math.ceil(this.count / TEX_WIDTH);
      this.order = new Uint32Array(rows * TEX_WIDTH);
      this.orderTex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
      gl.texStorage2D(gl.TEXTURE_2D, 1, gl.R32UI, TEX_WIDTH, rows);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
        gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      const corners = new Uint32Array(6 * this.count);
      for (let i = 0; i < this.count; i++) corners.set([0, 1, 2, 2, 1, 3].map((k) => 4 * i + k), 6 * i);
      gl.bindVertexArray(this.vao);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, gl.createBuffer());
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, corners, gl.STATIC_DRAW);
      gl.bindVertexArray(null);
    }

    _lineBuffer(positions, colors) {
      const gl = this.gl, vao = gl.createVertexArray();
      gl.bindVertexArray(vao);
      for (const [loc, data] of [[0, positions], [1, colors]]) {
        const b = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, b);
        gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
        gl.enableVertexAttribArray(loc);
        gl.vertexAttribPointer(loc, 3, gl.FLOAT, false, 0, 0);
      }
      gl.bindVertexArray(null);
      return { vao, count: positions.length / 3 };
    }

    _loadLines() { // a frustum per camera: held-out cameras orange, training cameras blue
      const pos = [], col = [];
      const size = this.scene.frustum_size || 0.1;
      for (const cam of this.scene.cameras) {
        const w = rigidInverse(cam.cam_from_world);
        const corners = [[0, 0], [cam.width, 0], [cam.width, cam.height], [0, cam.height]].map(
          ([u, v]) => {
            const d = [(u - cam.cx) / cam.fx * size, (v - cam.cy) / cam.fy * size, size];
            return [0, 1, 2].map((r) => w[4 * r] * d[0] + w[4 * r + 1] * d[1] + w[4 * r + 2] * d[2] + w[4 * r + 3]);
          });
        const c = cam.centre, color = cam.split === "test" ? [1, 0.55, 0.1] : [0.2, 0.5, 1];
        for (let k = 0; k < 4; k++) {
          pos.push(...c, ...corners[k], ...corners[k], ...corners[(k + 1) % 4]);
          for (let n = 0; n < 4; n++) col.push(...color);
        }
      }
      this.lines = this._lineBuffer(new Float32Array(pos), new Float32Array(col));
    }

    _loadPoints() { // 16-bit fractions of their bounding box, and RGB bytes
      const p = this.scene.points;
      if (!p) return;
      const q = decode(p.xyz16, Uint16Array), xyz = new Float32Array(q.length);
      for (let i = 0; i < q.length; i++)
        xyz[i] = p.lo[i % 3] + (q[i] / 65535) * (p.hi[i % 3] - p.lo[i % 3]);
      const rgb = decode(p.rgb, Uint8Array), colors = new Float32Array(rgb.length);
      for (let i = 0; i < rgb.length; i++) colors[i] = rgb[i] / 255;
      this.points = this._lineBuffer(xyz, colors);
    }

    _loadMesh() { // the run's mesh (a method without splats), and `recon mvs`'s when there is one
      this.mesh = this._meshBuffer(this.scene.mesh);
      this.mvsMesh = this._meshBuffer(this.scene.mvs_mesh);
      this.showMvs = Boolean(this.mvsMesh) && !this.mesh && !this.count;
    }

    _meshBuffer(m) {
      if (!m) return null;
      const gl = this.gl, rgb = decode(m.rgb, Uint8Array), colors = new Float32Array(rgb.length);
      for (let i = 0; i < rgb.length; i++) colors[i] = rgb[i] / 255;
      const mesh = this._lineBuffer(decode(m.xyz, Float32Array), colors);
      gl.bindVertexArray(mesh.vao);
      const faces = decode(m.faces, Uint32Array), ib = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, faces, gl.STATIC_DRAW);
      gl.bindVertexArray(null);
      return { vao: mesh.vao, count: faces.length };
    }

    // the view: cam_from_world (row-major, OpenCV), intrinsics and size in pixels. A camera's
    // view is drawn at DISPLAY_WIDTH (its field of view kept), or with `native` at the size
    // recon renders it (the browser tests compare the two).
    setCamera(i, native = false) {
      const cam = this.scene.cameras[i];
      this.current = i;
      this.view = {
        cam_from_world: Float64Array.from(cam.cam_from_world),
        fx: cam.fx, fy: cam.fy, cx: cam.cx, cy: cam.cy, width: cam.width, height: cam.height,
      };
      if (!native) {
        const s = DISPLAY_WIDTH / cam.width, v = this.view;
        Object.assign(v, { fx: v.fx * s, fy: v.fy * s, cx: v.cx * s, cy: v.cy * s,
          width: DISPLAY_WIDTH, height: Math.round(cam.height * s) });
      }
      this._resize(this.view.width, this.view.height);
      const photo = this.root.querySelector(".recon-photo");
      if (photo && cam.image) photo.src = (this.root.dataset.root || "") + cam.image;
      if (photo) photo.style.display = cam.image ? "" : "none";
      const label = this.root.querySelector(".recon-label");
      if (label) label.textContent = `${cam.split} camera ${cam.name}`;
      this.render();
    }

    // the current view at another size, the same field of view (the benchmark's 1280 x 720)
    setSize(width, height) {
      const v = this.view, sx = width / v.width, sy = height / v.height;
      Object.assign(v, { fx: v.fx * sx, fy: v.fy * sy, cx: v.cx * sx, cy: v.cy * sy, width, height });
      this._resize(width, height);
      this.render();
    }

    _resize(width, height) {
      const gl = this.gl;
      this.canvas.width = width;
      this.canvas.height = height;
      if (this.fbo) {
        gl.deleteFramebuffer(this.fbo);
        gl.deleteTexture(this.target_tex);
        gl.deleteRenderbuffer(this.depth);
      }
      this.target_tex = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, this.target_tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, width, height, 0, gl.RGBA, gl.FLOAT, null);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER])
        gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      this.depth = gl.createRenderbuffer();
      gl.bindRenderbuffer(gl.RENDERBUFFER, this.depth);
      gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
      this.fbo = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.target_tex, 0);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, this.depth);
    }

    // Back to front: a stable LSD radix sort of the depths along the optical axis (their float
    // bits, 8 at a time), read in reverse. recon's rasterizer sorts front to back, stable, so
    // splats at equal depth meet in the same order.
    // `candidates`: the splats to draw (all, in index order, or a moving view's prefix of the
    // most prominent), less those the shader would cull (`_visible`); returns how many
    _sort(view, candidates) {
      const keys = this.sortKeys || (this.sortKeys = new Uint32Array(this.count));
      let src = this.sortA || (this.sortA = new Uint32Array(this.count));
      let dst = this.sortB || (this.sortB = new Uint32Array(this.count));
      const n = this._visible(view, candidates, new Float32Array(keys.buffer), src);
      const counts = new Uint32Array(256);
      for (let shift = 0; shift < 32; shift += 8) {
        counts.fill(0);
        for (let i = 0; i < n; i++) counts[(keys[src[i]] >>> shift) & 255]++;
        for (let b = 0, sum = 0; b < 256; b++) { const c = counts[b]; counts[b] = sum; sum += c; }
        for (let i = 0; i < n; i++) { const j = src[i]; dst[counts[(keys[j] >>> shift) & 255]++] = j; }
        [src, dst] = [dst, src];
      }
      for (let i = 0; i < n; i++) this.order[i] = src[n - 1 - i];
      const gl = this.gl, rows = Math.ceil(n / TEX_WIDTH);
      gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, 0, TEX_WIDTH, rows, gl.RED_INTEGER, gl.UNSIGNED_INT,
        this.order.subarray(0, rows * TEX_WIDTH));
      return n;
    }

    // The candidates the shader would not cull into `out` (their depths into `depth`), a
    // software WebGL paying for every vertex it is given: in front of the near plane, opacity
    // over 1/255, and within a radius of the image no smaller than the shader's 3-sigma one
    // (the 2D covariance's largest eigenvalue is at most |J|^2 tr Sigma plus the dilations,
    // J the guard band's Jacobian at its widest). Returns how many.
    _visible(view, candidates, depth, out) {
      const m = view.cam_from_world, means = this.means, trace = this.trace, T = this.intervals;
      const { fx, fy, cx, cy, width: W, height: H } = view, near = this.scene.near || 0.01;
      const gx = (GUARD_BAND - 1) * W / (2 * fx), gy = (GUARD_BAND - 1) * H / (2 * fy);
      const ux = Math.max(cx / fx, (W - cx) / fx) + gx, uy = Math.max(cy / fy, (H - cy) / fy) + gy;
      const jj = fx * fx * (1 + ux * ux) + fy * fy * (1 + uy * uy);
      let n = 0;
      for (let k = 0; k < candidates.length; k++) {
        const i = candidates[k];
        if (!(this.opacity[i] * 255 > 1)) continue;
        const x = means[3 * i], y = means[3 * i + 1], zw = means[3 * i + 2];
        const z = m[8] * x + m[9] * y + m[10] * zw + m[11];
        if (!(z > near)) continue;
        const px = m[0] * x + m[1] * y + m[2] * zw + m[3], py = m[4] * x + m[5] * y + m[6] * zw + m[7];
        const ratio = T ? fx * T[i] / z : 0;
        const dil = DILATION * Math.max(1, ratio * ratio);
        const r = 3 * Math.sqrt(jj * trace[i] / (z * z) + 2 * dil + 0.4) + 1;
        const u = fx * px / z + cx, v = fy * py / z + cy;
        if (u + r <= 0 || u - r >= W || v + r <= 0 || v - r >= H) continue;
        depth[i] = z;
        out[n++] = i;
      }
      return n;
    }

    _uniforms(p, view) {
      const gl = this.gl, m = view.cam_from_world;
      const colMajor = new Float32Array(16);
      for (let i = 0; i < 4; i++) for (let j = 0; j < 4; j++) colMajor[4 * j + i] = m[4 * i + j];
      gl.uniformMatrix4fv(gl.getUniformLocation(p, "uView"), false, colMajor);
      gl.uniform4f(gl.getUniformLocation(p, "uIntr"), view.fx, view.fy, view.cx, view.cy);
      gl.uniform2f(gl.getUniformLocation(p, "uSize"), view.width, view.height);
      gl.uniform1f(gl.getUniformLocation(p, "uNear"), this.scene.near || 0.01);
    }

    // Draw the view: in full, or (`moving`) at the level of detail the last moving frame's
    // time allows (`nextLod`), in full again SETTLE_MS after the last move.
    render(moving = false) {
      const gl = this.gl, s = this.scene;
      const lod = moving ? this.lod || lodFor(this.fullMs || 0) : { scale: 1, share: 1 };
      const view = { ...this.view };
      if (lod.scale < 1) {
        const k = lod.scale;
        Object.assign(view, { fx: view.fx * k, fy: view.fy * k, cx: view.cx * k, cy: view.cy * k,
          width: Math.max(1, Math.round(view.width * k)), height: Math.max(1, Math.round(view.height * k)) });
      }
      clearTimeout(this.settle);
      if (moving) this.settle = setTimeout(() => this.render(), SETTLE_MS);
      const t0 = performance.now();
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fbo);
      gl.viewport(0, 0, view.width, view.height);
      const bg = s.background || [0, 0, 0];
      gl.clearColor(bg[0], bg[1], bg[2], 1);
      gl.clearDepth(1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      const meshes = [this.mesh, this.showMvs ? this.mvsMesh : null].filter(Boolean);
      if (meshes.length) {
        const p = this.programs.mesh;
        gl.useProgram(p);
        this._uniforms(p, view);
        gl.uniform1f(gl.getUniformLocation(p, "uFar"), s.far || 100);
        gl.enable(gl.DEPTH_TEST);
        for (const mesh of meshes) {
          gl.bindVertexArray(mesh.vao);
          gl.drawElements(gl.TRIANGLES, mesh.count, gl.UNSIGNED_INT, 0);
        }
        gl.disable(gl.DEPTH_TEST);
      }
      let drawn = 0, candidates = 0;
      if (this.count) {
        const share = Math.max(1, Math.round(lod.share * this.count));
        candidates = share < this.count ? this.prominent.subarray(0, share) : this.all;
        drawn = this._sort(view, candidates);
        const p = this.programs.splat;
        gl.useProgram(p);
        this._uniforms(p, view);
        const c = this._centre(view);
        gl.uniform3f(gl.getUniformLocation(p, "uCenter"), c[0], c[1], c[2]);
        gl.uniform1i(gl.getUniformLocation(p, "uDegree"), s.splats.sh_degree);
        gl.uniform1i(gl.getUniformLocation(p, "uAntialiased"), s.splats.antialiased ? 1 : 0);
        gl.uniform1i(gl.getUniformLocation(p, "uFootprint"), s.splats.intervals ? 1 : 0);
        const tile = view.width * view.height >= LARGE_IMAGE ? TILE_LARGE : TILE;
        gl.uniform1i(gl.getUniformLocation(p, "uTile"), tile);
        gl.activeTexture(gl.TEXTURE0);
        gl.bindTexture(gl.TEXTURE_2D, this.geomTex);
        gl.uniform1i(gl.getUniformLocation(p, "uGeom"), 0);
        gl.activeTexture(gl.TEXTURE1);
        gl.bindTexture(gl.TEXTURE_2D, this.shTex);
        gl.uniform1i(gl.getUniformLocation(p, "uSh"), 1);
        gl.activeTexture(gl.TEXTURE2);
        gl.bindTexture(gl.TEXTURE_2D, this.orderTex);
        gl.uniform1i(gl.getUniformLocation(p, "uOrder"), 2);
        gl.enable(gl.BLEND);
        gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
        gl.bindVertexArray(this.vao);
        gl.drawElements(gl.TRIANGLES, 6 * drawn, gl.UNSIGNED_INT, 0);
        gl.disable(gl.BLEND);
      }
      const p = this.programs.line;
      gl.useProgram(p);
      this._uniforms(p, view);
      if (this.showPoints && this.points) {
        gl.bindVertexArray(this.points.vao);
        gl.drawArrays(gl.POINTS, 0, this.points.count);
      }
      if (this.showCameras) {
        gl.bindVertexArray(this.lines.vao);
        gl.drawArrays(gl.LINES, 0, this.lines.count);
      }
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, this.view.width, this.view.height);
      const blit = this.programs.blit;
      gl.useProgram(blit);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.target_tex);
      gl.uniform1i(gl.getUniformLocation(blit, "uImage"), 0);
      gl.uniform2f(gl.getUniformLocation(blit, "uRegion"), view.width, view.height);
      gl.bindVertexArray(this.emptyVao);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
      gl.bindVertexArray(null);
      // a pixel read back: the frame is drawn (finish() need not wait for it)
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, this.pixel || (this.pixel = new Uint8Array(4)));
      this.frameMs = performance.now() - t0;
      this.drawn = { ...lod, gaussians: candidates.length || 0, visible: drawn,
        width: view.width, height: view.height };
      if (moving) this.lod = nextLod(lod, this.frameMs);
      else this.fullMs = this.frameMs;
    }

    _centre(view) {
      const w = rigidInverse(view.cam_from_world);
      return [w[3], w[7], w[11]];
    }

    // ---- orbit (left drag), pan (right or shift drag), zoom (wheel), reset -------------------
    _controls() {
      const c = this.canvas;
      let last = null, down = [0, 0], panning = false;
      c.addEventListener("contextmenu", (e) => e.preventDefault());
      c.addEventListener("pointerdown", (e) => {
        last = down = [e.clientX, e.clientY];
        panning = e.button === 2 || e.shiftKey;
        c.setPointerCapture(e.pointerId);
      });
      c.addEventListener("pointerup", (e) => {
        const moved = last && Math.hypot(e.clientX - down[0], e.clientY - down[1]) > 3;
        last = null;
        if (moved || e.button !== 0) return;
        const rect = c.getBoundingClientRect();  // a click on a camera flies to it
        const i = this.pickCamera((e.clientX - rect.left) * c.width / rect.width,
          (e.clientY - rect.top) * c.height / rect.height);
        if (i !== null) this.flyTo(i);
      });
      c.addEventListener("pointermove", (e) => {
        if (!last) return;
        const dx = e.clientX - last[0], dy = e.clientY - last[1];
        last = [e.clientX, e.clientY];
        if (panning) this.pan(dx, dy);
        else this.orbit(-dx * 0.005, -dy * 0.005);
      });
      c.addEventListener("wheel", (e) => {
        e.preventDefault();
        this.zoom(Math.exp(e.deltaY * 0.001));
      }, { passive: false });
    }

    // the camera whose centre is drawn within PICK_RADIUS px of canvas pixel (x, y), nearest
    // first (null: none), as the frusta are drawn (cameras shown)
    pickCamera(x, y) {
      if (!this.showCameras) return null;
      const m = this.view.cam_from_world, v = this.view;
      let best = null, bestD = PICK_RADIUS;
      this.scene.cameras.forEach((cam, i) => {
        const p = [0, 1, 2].map((r) => m[4 * r] * cam.centre[0] + m[4 * r + 1] * cam.centre[1] + m[4 * r + 2] * cam.centre[2] + m[4 * r + 3]);
        if (p[2] <= (this.scene.near || 0.01)) return;
        const d = Math.hypot(v.fx * p[0] / p[2] + v.cx - x, v.fy * p[1] / p[2] + v.cy - y);
        if (d < bestD) [best, bestD] = [i, d];
      });
      return best;
    }

    flyTo(i) {  // the list follows, and the photo
      this.setCamera(i);
      const list = this.root.querySelector(".recon-cameras");
      if (list) list.value = i;
    }

    _moveWorld(worldFromWorld) { // the camera moved by a world transform T: cam_from_world T^-1
      this.view.cam_from_world = matmul(this.view.cam_from_world, rigidInverse(worldFromWorld));
      this.render(true);
    }
    orbit(yaw, pitch) {
      const t = this.target, right = this._axis(0);
      const about = (axis, angle) => matmul(translation(t), matmul(rotation(axis, angle), translation(t.map((x) => -x))));
      this._moveWorld(matmul(about(right, pitch), about(this.up, yaw)));
    }
    pan(dx, dy) {
      const dist = this._distance(), f = this.view.fx;
      const r = this._axis(0), d = this._axis(1);
      const v = [0, 1, 2].map((k) => (-dx * r[k] - dy * d[k]) * dist / f);
      this.target = this.target.map((x, k) => x + v[k]);
      this._moveWorld(translation(v));
    }
    zoom(factor) {
      const c = this._centre(this.view), t = this.target;
      const v = [0, 1, 2].map((k) => (c[k] - t[k]) * (factor - 1));
      this._moveWorld(translation(v));
    }
    _axis(row) { // the camera's x (0) or y (1) axis in the world
      const m = this.view.cam_from_world;
      return [m[4 * row], m[4 * row + 1], m[4 * row + 2]];
    }
    _distance() {
      const c = this._centre(this.view);
      return Math.hypot(c[0] - this.target[0], c[1] - this.target[1], c[2] - this.target[2]);
    }

    // the canvas as a PNG data URL (the browser test compares it with `recon render`)
    snapshot() { return this.canvas.toDataURL("image/png"); }
  }

  function build(root) {
    const scene = (window.RECON_VIEWS || {})[root.dataset.view];
    const status = root.querySelector(".recon-status");
    try {
      if (!scene) throw new Error(`no scene ${root.dataset.view} (its script did not load)`);
      const viewer = new Viewer(root, scene);
      const list = root.querySelector(".recon-cameras");
      scene.cameras.forEach((cam, i) => {
        const o = document.createElement("option");
        o.value = i;
        o.textContent = `${cam.split} ${cam.name}`;
        list.appendChild(o);
      });
      list.value = viewer.current;
      list.addEventListener("change", () => viewer.setCamera(Number(list.value)));
      root.querySelector(".recon-reset").addEventListener("click", () => {
        viewer.target = viewer._sceneCentre();
        viewer.setCamera(Number(list.value));
      });
      const mvs = root.querySelector(".recon-mvs");
      if (mvs && !viewer.mvsMesh) mvs.style.display = "none";
      for (const [cls, key] of [[".recon-show-cameras", "showCameras"], [".recon-show-points", "showPoints"],
        [".recon-show-mvs", "showMvs"]]) {
        const box = root.querySelector(cls);
        if (!box) continue;
        box.checked = viewer[key];
        box.addEventListener("change", () => { viewer[key] = box.checked; viewer.render(); });
      }
      const what = viewer.count ? `${viewer.count} Gaussians` : viewer.mesh ? "mesh" : viewer.mvsMesh ? "mvs mesh" : "cameras";
      status.textContent = `${what}, ` +
        `${scene.cameras.length} cameras; drag to orbit, right-drag to pan, wheel to zoom`;
      return viewer;
    } catch (e) {
      status.textContent = `3D view unavailable: ${e.message}`;
      return null;
    }
  }

  // a packed scene's Gaussians decoded (asynchronously: the browser's gunzip) before its viewer
  async function prepare(root) {
    const scene = (window.RECON_VIEWS || {})[root.dataset.view];
    const s = scene && scene.splats;
    if (s && s.encoding === "pack" && !s.decoded)
      s.decoded = unpack(s, await gunzip(await packedBytes(s, root.dataset.src)));
  }

  window.reconViewers = {};
  window.reconLod = { nextLod, lodFor, FRAME_BUDGET_MS, MIN_SCALE, MIN_SHARE };
  async function start() {
    await Promise.all([...document.querySelectorAll(".recon-viewer")].map(async (root) => {
      try {
        await prepare(root);
      } catch (e) {
        root.querySelector(".recon-status").textContent = `3D view unavailable: ${e.message}`;
        window.reconViewers[root.dataset.view] = null;
        return;
      }
      window.reconViewers[root.dataset.view] = build(root);
    }));
    window.reconViewersReadyMs = performance.now();  // since the page began to load
    window.reconViewersReady = true;
  }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();

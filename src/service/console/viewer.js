'use strict';
// viewer.js: a small WebGL2 viewer for lightmapd's console. It draws a .glb (as the service
// exports it: meshes with POSITION, NORMAL, TEXCOORD_0, TEXCOORD_1, materials with base colour
// factors and textures, emission) with a half-float lightmap on TEXCOORD_1, each node's
// `extras.lightmap` page and rectangle applied (docs/conventions.md), and alpha as the bake
// reads it (MASK cut away below the cutoff, BLEND as stochastic coverage).
// Why not three.js: the page needs one mesh type, one material and one camera; three.js is
// ~650 kB minified and would need npm and a bundling step in the build (docs/console.md has
// the comparison). Limits: no skinning, morph targets, KTX2/Draco/meshopt, texture
// transforms, or sorted alpha blending; node matrices and TRS are applied.

// glTF component types to typed-array constructors.
const GLTF_ARRAY = {5120: Int8Array, 5121: Uint8Array, 5122: Int16Array, 5123: Uint16Array, 5125: Uint32Array, 5126: Float32Array};
const GLTF_SIZE = {SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4, MAT4: 16};

// Parses a .glb: its JSON, and a function reading an accessor as a typed array (copied out,
// de-interleaved, normalized integers scaled to 0..1).
function parseGlb(buf) {
  const dv = new DataView(buf);
  if (buf.byteLength < 20 || dv.getUint32(0, true) !== 0x46546c67) throw new Error('not a .glb file');
  let off = 12, json = null, bin = null;
  while (off + 8 <= buf.byteLength) {
    const len = dv.getUint32(off, true), type = dv.getUint32(off + 4, true);
    const body = new Uint8Array(buf, off + 8, len);
    if (type === 0x4e4f534a) json = JSON.parse(new TextDecoder().decode(body));
    else if (type === 0x004e4942) bin = body;
    off += 8 + len;
  }
  if (!json) throw new Error('the .glb has no JSON chunk');
  const view = i => {
    const v = json.bufferViews[i];
    if (v.buffer !== 0 || !bin) throw new Error('only the .glb\'s own buffer is supported');
    return {bytes: bin.subarray(v.byteOffset || 0, (v.byteOffset || 0) + v.byteLength), stride: v.byteStride || 0};
  };
  const accessor = i => {
    const a = json.accessors[i];
    const T = GLTF_ARRAY[a.componentType], n = GLTF_SIZE[a.type];
    const out = new (a.normalized ? Float32Array : T)(a.count * n);
    if (a.bufferView === undefined) return out;
    const {bytes, stride} = view(a.bufferView);
    const el = T.BYTES_PER_ELEMENT, step = stride || el * n;
    const src = new DataView(bytes.buffer, bytes.byteOffset + (a.byteOffset || 0));
    const get = {1: 'getInt8', 2: 'getInt16', 4: 'getInt32'}[el];
    const unsigned = T === Uint8Array || T === Uint16Array || T === Uint32Array;
    const reader = T === Float32Array ? 'getFloat32' : (unsigned ? get.replace('Int', 'Uint') : get);
    const scale = a.normalized ? (unsigned ? 2 ** (8 * el) - 1 : 2 ** (8 * el - 1) - 1) : 1;
    for (let k = 0; k < a.count; k++)
      for (let c = 0; c < n; c++) out[k * n + c] = src[reader](k * step + c * el, true) / scale;
    return out;
  };
  return {json, accessor, view};
}

// Column-major 4×4 matrices, just what the viewer needs.
const M4 = {
  identity: () => new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
  mul(a, b) {
    const o = new Float32Array(16);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      o[c * 4 + r] = s;
    }
    return o;
  },
  trs(t = [0, 0, 0], q = [0, 0, 0, 1], s = [1, 1, 1]) {
    const [x, y, z, w] = q;
    return new Float32Array([
      (1 - 2 * (y * y + z * z)) * s[0], 2 * (x * y + z * w) * s[0], 2 * (x * z - y * w) * s[0], 0,
      2 * (x * y - z * w) * s[1], (1 - 2 * (x * x + z * z)) * s[1], 2 * (y * z + x * w) * s[1], 0,
      2 * (x * z + y * w) * s[2], 2 * (y * z - x * w) * s[2], (1 - 2 * (x * x + y * y)) * s[2], 0,
      t[0], t[1], t[2], 1]);
  },
  perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
  },
  lookAt(eye, at, up) {
    const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    const norm = v => { const l = Math.hypot(...v) || 1; return v.map(x => x / l); };
    const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    const z = norm(sub(eye, at)), x = norm(cross(up, z)), y = cross(z, x);
    return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
  },
  apply(m, p) {
    return [0, 1, 2].map(r => m[r] * p[0] + m[4 + r] * p[1] + m[8 + r] * p[2] + m[12 + r]);
  },
};

const VS = `#version 300 es
layout(location=0) in vec3 pos; layout(location=1) in vec3 nrm;
layout(location=2) in vec2 uv0; layout(location=3) in vec2 uv1;
uniform mat4 viewProj, model; uniform vec4 lmScaleOffset;
out vec2 vUv0; out vec2 vUv1; out vec3 vN;
void main() {
  vUv0 = uv0; vUv1 = uv1 * lmScaleOffset.xy + lmScaleOffset.zw; vN = mat3(model) * nrm;
  gl_Position = viewProj * model * vec4(pos, 1.0);
}`;
const FS = `#version 300 es
precision highp float;
in vec2 vUv0; in vec2 vUv1; in vec3 vN;
uniform sampler2D lightmap, baseTex;
uniform vec4 baseColor; uniform vec3 emissive;
uniform int mode; uniform int hasLightmap; uniform float exposure;
uniform int alphaMode; uniform float alphaCutoff;
out vec4 color;
vec3 srgb(vec3 c) { return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c)); }
// A value in [0, 1) per pixel, for BLEND's stochastic coverage.
float hash(vec2 p) { return fract(sin(dot(p, vec2(12.9898, 78.233))) * 43758.5453); }
void main() {
  vec4 base = baseColor * texture(baseTex, vUv0);
  // Alpha as the bake reads it (docs/conventions.md): MASK keeps coverage >= cutoff, BLEND
  // covers a pixel with probability equal to its coverage; OPAQUE ignores alpha.
  if (alphaMode == 1 && base.a < alphaCutoff) discard;
  if (alphaMode == 2 && base.a <= hash(gl_FragCoord.xy)) discard;
  vec3 albedo = base.rgb;
  // Before the first snapshot: a plain headlight-free shade so the geometry reads.
  vec3 light = hasLightmap == 1 ? texture(lightmap, vUv1).rgb : vec3(0.25 + 0.2 * abs(normalize(vN).y));
  // The lightmap holds irradiance / pi: outgoing radiance is albedo times it (DESIGN §2).
  vec3 c = mode == 1 ? light : albedo * light + emissive;
  color = vec4(srgb(clamp(c * exposure, 0.0, 1.0)), 1.0);
}`;

// Light probes (docs/probes.md): a unit sphere per probe, shaded by the probe's radiance SH
// convolved with the cosine lobe, E(n)/pi = sum_i A_l c_i Y_i(n) / pi with A = pi, 2pi/3, pi/4:
// what a white diffuse sphere at the probe would show, so it reads like the walls beside it.
const PROBE_VS = `#version 300 es
layout(location=0) in vec3 pos;
uniform mat4 viewProj; uniform vec4 sphere;
out vec3 vN;
void main() { vN = pos; gl_Position = viewProj * vec4(sphere.xyz + pos * sphere.w, 1.0); }`;
const PROBE_FS = `#version 300 es
precision highp float;
in vec3 vN;
uniform vec3 sh[9]; uniform float exposure;
out vec4 color;
vec3 srgb(vec3 c) { return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c)); }
void main() {
  vec3 n = normalize(vN);
  float y[9] = float[9](0.282095, 0.488603 * n.y, 0.488603 * n.z, 0.488603 * n.x,
    1.092548 * n.x * n.y, 1.092548 * n.y * n.z, 0.315392 * (3.0 * n.z * n.z - 1.0), 1.092548 * n.x * n.z,
    0.546274 * (n.x * n.x - n.y * n.y));
  float band[9] = float[9](1.0, 0.666667, 0.666667, 0.666667, 0.25, 0.25, 0.25, 0.25, 0.25);
  vec3 e = vec3(0.0);
  for (int i = 0; i < 9; i++) e += sh[i] * band[i] * y[i];
  color = vec4(srgb(clamp(max(e, 0.0) * exposure, 0.0, 1.0)), 1.0);
}`;

// A UV sphere of unit radius (positions only; the normal is the position).
function sphereMesh(rings, segments) {
  const p = [], idx = [];
  for (let r = 0; r <= rings; r++) for (let s = 0; s <= segments; s++) {
    const th = Math.PI * r / rings, ph = 2 * Math.PI * s / segments;
    p.push(Math.sin(th) * Math.cos(ph), Math.cos(th), Math.sin(th) * Math.sin(ph));
  }
  for (let r = 0; r < rings; r++) for (let s = 0; s < segments; s++) {
    const a = r * (segments + 1) + s, b = a + segments + 1;
    idx.push(a, b, a + 1, a + 1, b, b + 1);
  }
  return {positions: new Float32Array(p), indices: new Uint16Array(idx)};
}

// The most probe spheres drawn (one draw call each); a denser set shows an even subset.
const MAX_PROBE_SPHERES = 4096;

class Viewer {
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext('webgl2', {antialias: true, preserveDrawingBuffer: true});
    if (!gl) throw new Error('this browser has no WebGL2');
    this.gl = gl;
    this.prog = this.program(VS, FS);
    this.u = {};
    for (const n of ['viewProj', 'model', 'lmScaleOffset', 'lightmap', 'baseTex', 'baseColor', 'emissive', 'mode', 'hasLightmap', 'exposure', 'alphaMode', 'alphaCutoff'])
      this.u[n] = gl.getUniformLocation(this.prog, n);
    this.white = this.texture(1, 1, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array([255, 255, 255, 255]));
    this.lightmap = null;
    this.draws = [];
    this.probes = [];
    this.mode = 0; this.nearest = false; this.exposureEv = 0;
    this.cam = {yaw: 0, pitch: 0.15, dist: 3, target: [0, 0, 0], home: null};
    this.controls();
    const ro = new ResizeObserver(() => this.resize());
    ro.observe(canvas);
  }

  program(vs, fs) {
    const gl = this.gl, p = gl.createProgram();
    for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
      const s = gl.createShader(type);
      gl.shaderSource(s, src); gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error('shader: ' + gl.getShaderInfoLog(s));
      gl.attachShader(p, s);
    }
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error('program: ' + gl.getProgramInfoLog(p));
    return p;
  }

  texture(w, h, internal, format, type, data) {
    const gl = this.gl, t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data);
    for (const [k, v] of [[gl.TEXTURE_MIN_FILTER, gl.LINEAR], [gl.TEXTURE_MAG_FILTER, gl.LINEAR], [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]])
      gl.texParameteri(gl.TEXTURE_2D, k, v);
    return t;
  }

  // Loads a .glb's meshes (replacing what was shown); resolves when its textures are decoded.
  async load(buf) {
    const gl = this.gl, {json, accessor, view} = parseGlb(buf);
    for (const d of this.draws) { gl.deleteVertexArray(d.vao); d.buffers.forEach(b => gl.deleteBuffer(b)); }
    this.draws = [];
    const images = await Promise.all((json.images || []).map(async img => {
      if (img.bufferView === undefined) return null;
      const blob = new Blob([view(img.bufferView).bytes], {type: img.mimeType || 'image/png'});
      const bmp = await createImageBitmap(blob, {colorSpaceConversion: 'none'});
      const t = this.texture(bmp.width, bmp.height, gl.SRGB8_ALPHA8, gl.RGBA, gl.UNSIGNED_BYTE, bmp);
      gl.generateMipmap(gl.TEXTURE_2D);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR_MIPMAP_LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.REPEAT);
      return t;
    }));
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    const visit = (ni, parent) => {
      const n = json.nodes[ni];
      const local = n.matrix ? new Float32Array(n.matrix) : M4.trs(n.translation, n.rotation, n.scale);
      const m = M4.mul(parent, local);
      if (n.mesh !== undefined) for (const prim of json.meshes[n.mesh].primitives) {
        if ((prim.mode ?? 4) !== 4 || prim.attributes.POSITION === undefined) continue;
        const pos = accessor(prim.attributes.POSITION);
        for (let i = 0; i < pos.length; i += 3) {
          const p = M4.apply(m, [pos[i], pos[i + 1], pos[i + 2]]);
          for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
        }
        const d = this.primitive(prim, pos, accessor, m, json.materials?.[prim.material], images, json.textures);
        // Where the node's lightmap is (docs/conventions.md): its page and the rectangle in it.
        const lm = n.extras?.lightmap;
        d.page = Number.isInteger(lm?.page) ? lm.page : 0;
        d.scaleOffset = Array.isArray(lm?.scale_offset) && lm.scale_offset.length === 4 ? lm.scale_offset : [1, 1, 0, 0];
        this.draws.push(d);
      }
      for (const c of n.children || []) visit(c, m);
    };
    const roots = json.scenes?.[json.scene ?? 0]?.nodes ?? json.nodes.map((_, i) => i);
    for (const r of roots) visit(r, M4.identity());
    if (!this.draws.length) throw new Error('the scene has no triangles to show');
    const center = lo.map((v, k) => (v + hi[k]) / 2);
    const radius = Math.max(1e-3, Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) / 2);
    this.cam.home = {target: center, dist: radius * 1.6, yaw: 0, pitch: 0.08, radius};
    this.resetView();
  }

  primitive(prim, pos, accessor, model, mat, images, textures) {
    const gl = this.gl, vao = gl.createVertexArray(), buffers = [];
    gl.bindVertexArray(vao);
    const count = pos.length / 3;
    const attr = (loc, data, n) => {
      const b = gl.createBuffer(); buffers.push(b);
      gl.bindBuffer(gl.ARRAY_BUFFER, b);
      gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, n, gl.FLOAT, false, 0, 0);
    };
    const a = prim.attributes, f32 = i => Float32Array.from(accessor(i));
    attr(0, pos, 3);
    attr(1, a.NORMAL !== undefined ? f32(a.NORMAL) : new Float32Array(count * 3), 3);
    attr(2, a.TEXCOORD_0 !== undefined ? f32(a.TEXCOORD_0) : new Float32Array(count * 2), 2);
    attr(3, a.TEXCOORD_1 !== undefined ? f32(a.TEXCOORD_1) : new Float32Array(count * 2), 2);
    let indexType = null, n = count;
    if (prim.indices !== undefined) {
      const idx = Uint32Array.from(accessor(prim.indices));
      const b = gl.createBuffer(); buffers.push(b);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, b);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, idx, gl.STATIC_DRAW);
      indexType = gl.UNSIGNED_INT; n = idx.length;
    }
    gl.bindVertexArray(null);
    const pbr = mat?.pbrMetallicRoughness || {};
    const strength = mat?.extensions?.KHR_materials_emissive_strength?.emissiveStrength ?? 1;
    const texIndex = pbr.baseColorTexture?.index;
    const tex = texIndex !== undefined ? images[textures?.[texIndex]?.source] : null;
    return {vao, buffers, n, indexType, model, hasUv1: a.TEXCOORD_1 !== undefined,
      baseColor: pbr.baseColorFactor || [1, 1, 1, 1], tex: tex || this.white,
      alphaMode: {MASK: 1, BLEND: 2}[mat?.alphaMode] || 0, alphaCutoff: mat?.alphaCutoff ?? 0.5,
      emissive: (mat?.emissiveFactor || [0, 0, 0]).map(v => v * strength)};
  }

  // The probes of a probes.json body: valid ones drawn as spheres of `radius` (default: a
  // fifth of the smallest distance between distinct probes, within 0.2 % to 3 % of the
  // scene's size).
  setProbes(set, radius) {
    const gl = this.gl;
    if (!this.probeProg) {
      this.probeProg = this.program(PROBE_VS, PROBE_FS);
      this.pu = {};
      for (const n of ['viewProj', 'sphere', 'sh', 'exposure']) this.pu[n] = gl.getUniformLocation(this.probeProg, n);
      const m = sphereMesh(12, 24);
      this.probeVao = gl.createVertexArray();
      gl.bindVertexArray(this.probeVao);
      const vb = gl.createBuffer();
      gl.bindBuffer(gl.ARRAY_BUFFER, vb);
      gl.bufferData(gl.ARRAY_BUFFER, m.positions, gl.STATIC_DRAW);
      gl.enableVertexAttribArray(0);
      gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
      const ib = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, m.indices, gl.STATIC_DRAW);
      gl.bindVertexArray(null);
      this.probeCount = m.indices.length;
    }
    let valid = (set?.probes || []).filter(p => p.valid);
    if (valid.length > MAX_PROBE_SPHERES) {
      const k = valid.length / MAX_PROBE_SPHERES;
      valid = Array.from({length: MAX_PROBE_SPHERES}, (_, i) => valid[Math.floor(i * k)]);
    }
    const size = this.cam.home?.radius || 1;
    if (!radius) {
      // The nearest distinct neighbour (a given probe may sit on a grid point).
      let d = Infinity;
      for (let i = 0; i < Math.min(valid.length, 256); i++) for (let j = 0; j < valid.length; j++) {
        const e = Math.hypot(...valid[i].position.map((v, k) => v - valid[j].position[k]));
        if (e > size * 1e-4) d = Math.min(d, e);
      }
      radius = Math.min(Math.max(isFinite(d) ? d / 5 : size * 0.02, size * 0.002), size * 0.03);
    }
    this.probes = valid.map(p => ({sphere: [...p.position, radius], sh: new Float32Array(p.sh.flat())}));
    this.draw();
    return this.probes.length;
  }

  // A lightmap of w×h texels of four half floats each (the service's lightmap.rgba16f).
  setLightmap(w, h, halves) {
    const gl = this.gl;
    if (this.lightmap) gl.deleteTexture(this.lightmap);
    this.lightmap = this.texture(w, h, gl.RGBA16F, gl.RGBA, gl.HALF_FLOAT, halves);
    this.lightmapSize = [w, h];
    this.setFilter(this.nearest);
  }

  setFilter(nearest) {
    const gl = this.gl;
    this.nearest = nearest;
    if (this.lightmap) {
      gl.bindTexture(gl.TEXTURE_2D, this.lightmap);
      const f = nearest ? gl.NEAREST : gl.LINEAR;
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, f);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, f);
    }
    this.draw();
  }
  setMode(lightmapOnly) { this.mode = lightmapOnly ? 1 : 0; this.draw(); }
  setExposure(ev) { this.exposureEv = ev; this.draw(); }

  resetView() {
    const h = this.cam.home;
    if (h) Object.assign(this.cam, {target: h.target.slice(), dist: h.dist, yaw: h.yaw, pitch: h.pitch});
    this.draw();
  }

  eye() {
    const c = this.cam, cp = Math.cos(c.pitch);
    return [c.target[0] + c.dist * cp * Math.sin(c.yaw), c.target[1] + c.dist * Math.sin(c.pitch), c.target[2] + c.dist * cp * Math.cos(c.yaw)];
  }

  // Moves the target along the camera's own axes (pan, and fly with W A S D).
  move(right, up, forward) {
    const c = this.cam, e = this.eye();
    const f = [c.target[0] - e[0], c.target[1] - e[1], c.target[2] - e[2]].map(v => v / c.dist);
    const r = [Math.cos(c.yaw), 0, -Math.sin(c.yaw)];
    const u = [f[1] * r[2] - f[2] * r[1], f[2] * r[0] - f[0] * r[2], f[0] * r[1] - f[1] * r[0]].map(v => -v);
    for (let k = 0; k < 3; k++) c.target[k] += r[k] * right + u[k] * up + f[k] * forward;
    this.draw();
  }

  controls() {
    const cv = this.canvas, c = this.cam;
    let drag = null;
    cv.addEventListener('contextmenu', e => e.preventDefault());
    cv.addEventListener('pointerdown', e => { drag = {x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey}; cv.setPointerCapture(e.pointerId); cv.focus(); });
    cv.addEventListener('pointerup', () => { drag = null; });
    cv.addEventListener('pointermove', e => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (drag.pan) { const s = c.dist / cv.clientHeight; this.move(-dx * s, dy * s, 0); }
      else { c.yaw -= dx * 0.01; c.pitch = Math.max(-1.5, Math.min(1.5, c.pitch + dy * 0.01)); this.draw(); }
    });
    cv.addEventListener('wheel', e => { e.preventDefault(); c.dist *= Math.exp(e.deltaY * 0.001); this.draw(); }, {passive: false});
    cv.addEventListener('keydown', e => {
      const step = (c.home?.radius || 1) * 0.1;
      const keys = {
        ArrowLeft: () => { c.yaw += 0.1; }, ArrowRight: () => { c.yaw -= 0.1; },
        ArrowUp: () => { c.pitch = Math.min(1.5, c.pitch + 0.1); }, ArrowDown: () => { c.pitch = Math.max(-1.5, c.pitch - 0.1); },
        '+': () => { c.dist *= 0.9; }, '=': () => { c.dist *= 0.9; }, '-': () => { c.dist /= 0.9; },
        w: () => this.move(0, 0, step), s: () => this.move(0, 0, -step), a: () => this.move(-step, 0, 0), d: () => this.move(step, 0, 0),
      };
      const k = keys[e.key];
      if (k) { e.preventDefault(); k(); this.draw(); }
    });
  }

  resize() {
    const cv = this.canvas, dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(cv.clientWidth * dpr)), h = Math.max(1, Math.round(cv.clientHeight * dpr));
    if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
    this.draw();
  }

  draw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  render() {
    const gl = this.gl, cv = this.canvas, c = this.cam;
    gl.viewport(0, 0, cv.width, cv.height);
    gl.clearColor(0.047, 0.051, 0.059, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!this.draws.length) return;
    gl.enable(gl.DEPTH_TEST);
    gl.useProgram(this.prog);
    const r = c.home?.radius || 1;
    const proj = M4.perspective(0.9, cv.width / cv.height, Math.max(c.dist - 4 * r, r * 1e-3), c.dist + 4 * r);
    gl.uniformMatrix4fv(this.u.viewProj, false, M4.mul(proj, M4.lookAt(this.eye(), c.target, [0, 1, 0])));
    gl.uniform1i(this.u.mode, this.mode);
    gl.uniform1f(this.u.exposure, 2 ** this.exposureEv);
    gl.uniform1i(this.u.lightmap, 0);
    gl.uniform1i(this.u.baseTex, 1);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, this.lightmap || this.white);
    // The lightmap is the bake's grid: its W x W pages one under another, so page P's
    // v in [0, 1] is rows [P W, (P + 1) W) of the H rows.
    const [lw, lh] = this.lightmapSize || [1, 1], k = lw / lh;
    for (const d of this.draws) {
      const [sx, sy, ox, oy] = d.scaleOffset;
      gl.uniform4f(this.u.lmScaleOffset, sx, sy * k, ox, (d.page + oy) * k);
      gl.uniform1i(this.u.hasLightmap, this.lightmap && d.hasUv1 ? 1 : 0);
      gl.uniformMatrix4fv(this.u.model, false, d.model);
      gl.uniform4fv(this.u.baseColor, d.baseColor);
      gl.uniform1i(this.u.alphaMode, d.alphaMode);
      gl.uniform1f(this.u.alphaCutoff, d.alphaCutoff);
      gl.uniform3fv(this.u.emissive, d.emissive);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, d.tex);
      gl.bindVertexArray(d.vao);
      if (d.indexType) gl.drawElements(gl.TRIANGLES, d.n, d.indexType, 0);
      else gl.drawArrays(gl.TRIANGLES, 0, d.n);
    }
    gl.bindVertexArray(null);
    if (this.probes.length) {
      gl.useProgram(this.probeProg);
      gl.uniformMatrix4fv(this.pu.viewProj, false, M4.mul(proj, M4.lookAt(this.eye(), c.target, [0, 1, 0])));
      gl.uniform1f(this.pu.exposure, 2 ** this.exposureEv);
      gl.bindVertexArray(this.probeVao);
      for (const p of this.probes) {
        gl.uniform4fv(this.pu.sphere, p.sphere);
        gl.uniform3fv(this.pu.sh, p.sh);
        gl.drawElements(gl.TRIANGLES, this.probeCount, gl.UNSIGNED_SHORT, 0);
      }
      gl.bindVertexArray(null);
    }
    this.frames = (this.frames || 0) + 1;
  }
}

'use strict';
// app.js: the console's logic. Every request goes through api(), which adds the bearer token
// (kept in sessionStorage) and turns problem+json answers into errors carrying the problem.
// Text from the server (scene and mesh names, failure reasons) is only ever set as textContent
// or escaped with esc(): it never becomes HTML.

const $ = id => document.getElementById(id);
const esc = s => String(s ?? '').replace(/[&<>"']/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'}[c]));
const state = {token: sessionStorage.getItem('lightmapd-token') || '', techniques: null, scenes: [], job: null,
  stream: null, viewer: null, geometryFor: null, lightmap: null, lightmapKey: null, snapshotSeen: 0,
  rendering: null};

class ApiError extends Error {
  constructor(status, problem) { super(problem.detail || problem.title || ('HTTP ' + status)); this.status = status; this.problem = problem; }
}

function authHeaders(extra = {}) {
  const token = state.token;
  return token ? {...extra, 'Authorization': 'Bearer ' + token} : extra;
}

async function api(path, opts = {}) {
  const r = await fetch(path, {...opts, headers: authHeaders(opts.headers || {})});
  if (r.status === 401) { askToken(r); throw new ApiError(401, {detail: 'a token is required'}); }
  if (!r.ok) {
    const p = await r.json().catch(() => ({detail: r.statusText}));
    throw new ApiError(r.status, p);
  }
  return r;
}
const json = async (path, opts) => (await api(path, opts)).json();

// --- token ---------------------------------------------------------------------------------
let loginShown = false;
async function askToken(r) {
  const p = await r.clone().json().catch(() => ({}));
  $('login-why').textContent = state.token ? (p.detail || 'the token was refused') : '';
  $('login').hidden = false;
  if (!loginShown) { $('token').focus(); loginShown = true; }
}
$('login').addEventListener('submit', e => {
  e.preventDefault();
  state.token = $('token').value.trim();
  sessionStorage.setItem('lightmapd-token', state.token);
  $('login').hidden = true; loginShown = false;
  start();
});

// Links marked data-fetch are fetched with the token and opened or saved from a blob URL
// (a plain link cannot carry the header, and the token never goes into a URL).
document.addEventListener('click', async e => {
  const a = e.target.closest('a[data-fetch]');
  if (!a) return;
  e.preventDefault();
  try {
    const blob = await (await api(a.getAttribute('href'))).blob();
    const url = URL.createObjectURL(blob);
    const save = document.createElement('a');
    save.href = url;
    if (a.dataset.fetch) save.download = a.dataset.fetch; else save.target = '_blank';
    save.click();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
  } catch (err) { if (err.status !== 401) $('form-error').textContent = err.message; }
});

// --- scenes --------------------------------------------------------------------------------
const drop = $('drop');
for (const ev of ['dragenter', 'dragover']) drop.addEventListener(ev, e => { e.preventDefault(); drop.classList.add('over'); });
for (const ev of ['dragleave', 'drop']) drop.addEventListener(ev, () => drop.classList.remove('over'));
drop.addEventListener('drop', e => { e.preventDefault(); upload([...e.dataTransfer.files]); });
drop.addEventListener('keydown', e => { if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); $('file').click(); } });
$('file').addEventListener('change', e => { upload([...e.target.files]); e.target.value = ''; });

async function upload(files) {
  if (!files.length) return;
  const status = $('upload-status');
  const gltf = files.filter(f => /\.gltf$/i.test(f.name));
  const glb = files.filter(f => /\.glb$/i.test(f.name));
  let body, headers = {};
  if (glb.length === 1 && files.length === 1) { body = files[0]; headers['Content-Type'] = 'model/gltf-binary'; }
  else if (gltf.length === 1 && !glb.length) {
    body = new FormData();
    for (const f of files) body.append(f.name, f, f.name);
  } else {
    status.innerHTML = '<span class="error">Drop one .glb, or one .gltf together with the files it names.</span>';
    return;
  }
  status.textContent = `Uploading ${files.map(f => f.name).join(', ')} (${fmtBytes(files.reduce((s, f) => s + f.size, 0))})…`;
  $('report').innerHTML = '';
  try {
    const r = await api('/v1/scenes', {method: 'POST', body, headers});
    const scene = await r.json();
    status.textContent = r.status === 201 ? 'Uploaded and imported.' : 'This scene was uploaded before: the same scene.';
    showReport(scene, await meshesWithoutUv1(files));
    await loadScenes(scene.id);
  } catch (err) {
    status.innerHTML = `<span class="error">Upload refused (${err.status}): ${esc(err.message)}</span>` +
      (err.problem?.field ? ` <span class="hint">field: ${esc(err.problem.field)}</span>` : '');
  }
}

// Meshes without TEXCOORD_1 (they get generated lightmap UVs), read from the uploaded file
// itself: the import report says only whether every mesh has them.
async function meshesWithoutUv1(files) {
  try {
    let gltf;
    const glb = files.find(f => /\.glb$/i.test(f.name)), text = files.find(f => /\.gltf$/i.test(f.name));
    if (glb) gltf = parseGlb(await glb.arrayBuffer()).json;
    else if (text) gltf = JSON.parse(await text.text());
    else return null;
    return (gltf.meshes || []).map((m, i) => ({name: m.name || `mesh ${i}`, missing: (m.primitives || []).some(p => p.attributes?.TEXCOORD_1 === undefined)}))
      .filter(m => m.missing).map(m => m.name);
  } catch { return null; }
}

function showReport(scene, generated) {
  const r = scene.report || {};
  const b = (r.bounds_min && r.bounds_max) ? r.bounds_min.map((v, k) => (r.bounds_max[k] - v).toFixed(2)).join(' × ') : '–';
  const uvs = r.has_lightmap_uvs ? 'every mesh has TEXCOORD_1: baked as they are'
    : 'generated by the engine for ' + (generated?.length ? generated.join(', ') : 'the meshes without TEXCOORD_1');
  const rows = [
    ['meshes', `${r.meshes ?? '–'} (${r.primitives ?? '–'} primitives)`], ['triangles', r.triangles ?? '–'],
    ['materials', r.materials ?? '–'], ['textures', r.textures ?? '–'], ['lights', r.lights ?? '–'],
    ['emissive triangles', r.emissive_triangles ?? '–'], ['size', b + ' m'], ['lightmap UVs', uvs],
  ];
  if (r.degenerate_triangles) rows.push(['dropped (no area)', r.degenerate_triangles]);
  if (r.zero_uv_area_triangles) rows.push(['no lightmap UV area', r.zero_uv_area_triangles]);
  const warnings = r.warnings || [];
  $('report').innerHTML = `<div class="report"><h3>Import report · ${esc(scene.files.join(', '))}</h3><table>` +
    rows.map(([k, v]) => `<tr><th scope="row">${esc(k)}</th><td>${esc(v)}</td></tr>`).join('') + '</table>' +
    (warnings.length ? '<ul>' + warnings.map(w => `<li class="warn">${esc(w)}</li>`).join('') + '</ul>' : '<p class="hint">No warnings.</p>') +
    '</div>';
}

async function loadScenes(select) {
  const {scenes} = await json('/v1/scenes');
  state.scenes = scenes;
  const list = $('scene-list');
  list.innerHTML = scenes.length ? '' : '<li class="hint">No scenes yet.</li>';
  for (const s of scenes) {
    const li = document.createElement('li');
    li.innerHTML = `<span class="name"></span><span class="hint"></span><button type="button" class="show">Report</button><button type="button" class="del" aria-label="Delete scene">Delete</button>`;
    li.querySelector('.name').textContent = s.files.find(f => /\.(glb|gltf)$/i.test(f)) || s.id;
    li.querySelector('.name').title = s.id;
    li.querySelector('.hint').textContent = `${s.report?.triangles ?? '?'} tris · ${fmtBytes(s.size_bytes)}`;
    li.querySelector('.show').onclick = () => { showReport(s); $('f-scene').value = s.id; refreshReferences().catch(() => {}); };
    li.querySelector('.del').onclick = async () => {
      try { await api('/v1/scenes/' + s.id, {method: 'DELETE'}); $('upload-status').textContent = 'Scene deleted.'; }
      catch (err) { $('upload-status').innerHTML = `<span class="error">${esc(err.message)}</span>`; }
      loadScenes();
    };
    list.append(li);
  }
  const sel = $('f-scene'), keep = select || sel.value;
  sel.innerHTML = scenes.map(s => `<option value="${esc(s.id)}">${esc((s.files.find(f => /\.(glb|gltf)$/i.test(f)) || '') + ' · ' + s.id.slice(0, 8))}</option>`).join('');
  if (scenes.some(s => s.id === keep)) sel.value = keep;
  refreshReferences().catch(() => {});
}

// --- bake form (built from GET /v1/techniques) ------------------------------------------------
async function loadTechniques() {
  const t = await json('/v1/techniques');
  state.techniques = t;
  $('f-technique').innerHTML = t.techniques.map(x => `<option value="${esc(x.id)}">${esc(x.id)}</option>`).join('');
  $('f-technique').value = t.defaults.technique;
  $('f-resolution').value = t.defaults.resolution;
  $('f-resolution').title = `1 to ${t.limits.max_resolution} on this server`;
  $('f-steps').value = t.defaults.stop.steps ?? '';
  $('f-seconds').value = t.defaults.stop.seconds ?? '';
  $('f-target').value = t.defaults.stop.target_error != null ? +(t.defaults.stop.target_error * 100).toFixed(4) : '';
  $('f-steps').title = `at most ${t.limits.max_job_steps} on this server`;
  $('f-seconds').title = `at most ${t.limits.max_job_seconds} s on this server`;
  $('f-outputs').innerHTML = t.outputs.map((o, i) =>
    `<label class="check field"><input type="checkbox" value="${esc(o)}"> ${esc(o)}</label>`).join('');
  // A choice this server cannot run stays listed, disabled, with the reason as its title.
  $('f-denoise').innerHTML = t.denoisers.map(d =>
    `<option value="${esc(d.id)}"${d.available ? '' : ' disabled'} title="${esc(d.detail)}">${esc(d.id)}${d.available ? '' : ' (not on this server)'}</option>`).join('');
  $('f-denoise').value = 'auto';
  denoiserChanged();
  techniqueChanged();
}

function techniqueChanged() {
  const t = state.techniques.techniques.find(x => x.id === $('f-technique').value);
  if (!t) return;
  const left = t.left_out.map(i => `${i.name} (${i.why})`);
  const lights = t.lights.map(l => l.replaceAll('_', ' ')).join(', ');
  $('technique-note').textContent = t.summary + '. Bakes: ' + lights + '; writes: ' + t.outputs.join(', ') + ' (a job asking for other light or layers is refused). ' +
    (left.length ? 'Leaves out: ' + left.join('; ') + '. ' : '') + 'Error estimate: ' + t.error_estimate + '.';
  const box = $('f-params');
  box.innerHTML = '';
  for (const [k, v] of Object.entries(t.params)) {
    const label = document.createElement('label');
    label.className = 'field';
    label.dataset.field = 'params.' + k;
    label.append(k + ' ');
    const input = document.createElement('input');
    input.dataset.param = k;
    if (typeof v === 'boolean') { input.type = 'checkbox'; input.checked = v; label.className = 'check field'; }
    else if (typeof v === 'number') { input.type = 'number'; input.step = 'any'; input.value = v; }
    else { input.type = 'text'; input.value = v == null ? '' : (typeof v === 'object' ? JSON.stringify(v) : v); input.placeholder = v == null ? 'default' : ''; }
    input.dataset.initial = input.type === 'checkbox' ? String(input.checked) : input.value;
    label.append(input);
    box.append(label);
  }
}
$('f-technique').addEventListener('change', techniqueChanged);

function denoiserChanged() {
  const d = state.techniques.denoisers.find(x => x.id === $('f-denoise').value);
  $('denoise-note').textContent = d ? d.summary + (d.id === 'auto' ? ' (here: ' + d.detail + ')' : '') + '.' : '';
}
$('f-denoise').addEventListener('change', denoiserChanged);
for (const [on, ids] of [['f-sky-on', ['f-sky', 'f-sky-hemi']], ['f-sun-on', ['f-sun', 'f-sun-dir']]])
  $(on).addEventListener('change', () => { for (const i of ids) $(i).disabled = !$(on).checked; drawDial(); });

// Sun direction on a hemisphere dial: the centre is straight down (sun overhead), the rim the
// horizon; x to the right, z down the dial. The typed field and the dial follow each other.
const dial = $('sun-dial');
function sunDir() { return $('f-sun-dir').value.split(',').map(Number); }
function drawDial() {
  const g = dial.getContext('2d'), R = 50, c = 56;
  g.clearRect(0, 0, 112, 112);
  g.strokeStyle = '#556'; g.lineWidth = 1;
  for (const r of [R, R * Math.cos(Math.PI / 6), R * Math.cos(Math.PI / 3)]) { g.beginPath(); g.arc(c, c, r, 0, 7); g.stroke(); }
  g.fillStyle = '#a0a7b0'; g.font = '10px sans-serif'; g.fillText('+x', 96, 60); g.fillText('+z', 52, 110);
  const d = sunDir();
  const l = Math.hypot(...d);
  if (!(l > 0) || !$('f-sun-on').checked) return;
  // From the sun toward the scene: the sun itself sits at -d.
  const s = d.map(v => -v / l);
  g.fillStyle = s[1] > 0 ? '#f0b849' : '#ff7a6b';
  g.beginPath(); g.arc(c + s[0] * R, c + s[2] * R, 6, 0, 7); g.fill();
}
function setSunFrom(x, z) {
  const r = Math.hypot(x, z);
  if (r > 1) { x /= r; z /= r; }
  const y = Math.sqrt(Math.max(0, 1 - x * x - z * z));
  $('f-sun-dir').value = [-x, -y, -z].map(v => +v.toFixed(3)).join(', ');
  drawDial();
}
dial.addEventListener('click', e => {
  if (!$('f-sun-on').checked) { $('f-sun-on').click(); }
  const b = dial.getBoundingClientRect();
  setSunFrom((e.clientX - b.left - 56) / 50, (e.clientY - b.top - 56) / 50);
});
dial.addEventListener('keydown', e => {
  const d = sunDir(), l = Math.hypot(...d) || 1;
  const s = d.map(v => -v / l);
  let az = Math.atan2(s[2], s[0]), el = Math.asin(Math.max(-1, Math.min(1, s[1])));
  const k = {ArrowLeft: () => { az -= 0.1; }, ArrowRight: () => { az += 0.1; }, ArrowUp: () => { el = Math.min(Math.PI / 2, el + 0.05); }, ArrowDown: () => { el = Math.max(0.02, el - 0.05); }}[e.key];
  if (!k) return;
  e.preventDefault();
  if (!$('f-sun-on').checked) $('f-sun-on').click();
  k();
  setSunFrom(Math.cos(el) * Math.cos(az), Math.cos(el) * Math.sin(az));
});
$('f-sun-dir').addEventListener('input', drawDial);

function numbers(id) { return $(id).value.split(',').map(s => s.trim()).filter(s => s !== '').map(Number); }
function num(id) { const v = $(id).value.trim(); return v === '' ? undefined : Number(v); }

function buildBody() {
  const body = {scene: $('f-scene').value, technique: $('f-technique').value, resolution: num('f-resolution'), priority: num('f-priority') ?? 0};
  // Generated UVs: how they are made, and at what density (blank: the highest that fits a page).
  if ($('f-uvs').value !== 'generate-missing') body.lightmap_uvs = $('f-uvs').value;
  if (num('f-density') !== undefined) body.texels_per_unit = num('f-density');
  const stop = {};
  if (num('f-steps') !== undefined) stop.steps = num('f-steps');
  if (num('f-seconds') !== undefined) stop.seconds = num('f-seconds');
  if (num('f-target') !== undefined) stop.target_error = num('f-target') / 100;
  body.stop = stop;
  const lighting = {};
  if ($('f-sky-on').checked) lighting.sky = {radiance: numbers('f-sky'), hemisphere: $('f-sky-hemi').value};
  if ($('f-sun-on').checked) lighting.sun = {direction: numbers('f-sun-dir'), radiance: numbers('f-sun')};
  if (Object.keys(lighting).length) body.lighting = lighting;
  // outputs[k] in a 422 is the k-th layer sent: label the checked boxes so.
  const checked = [...$('f-outputs').querySelectorAll('input:checked')];
  for (const l of $('f-outputs').querySelectorAll('label')) delete l.dataset.field;
  checked.forEach((i, k) => { i.closest('label').dataset.field = `outputs[${k}]`; });
  body.outputs = checked.map(i => i.value);
  body.denoise = $('f-denoise').value;
  if ($('f-reference').value) body.reference = $('f-reference').value;
  const params = {};
  for (const input of $('f-params').querySelectorAll('input')) {
    const now = input.type === 'checkbox' ? String(input.checked) : input.value;
    if (now === input.dataset.initial) continue;  // unchanged: the technique's default applies
    const k = input.dataset.param;
    if (input.type === 'checkbox') params[k] = input.checked;
    else if (input.type === 'number') params[k] = Number(input.value);
    else { try { params[k] = JSON.parse(input.value); } catch { params[k] = input.value; } }
  }
  if (Object.keys(params).length) body.params = params;
  return body;
}

function clearFieldErrors() {
  for (const el of document.querySelectorAll('#bake-form .invalid')) el.classList.remove('invalid');
  for (const el of document.querySelectorAll('#bake-form .field-error')) el.remove();
  for (const el of document.querySelectorAll('#bake-form [aria-invalid]')) el.removeAttribute('aria-invalid');
  $('form-error').textContent = '';
  $('form-warning').textContent = '';
}

// Shows a 422 by the field it names: the form element whose data-field is the field, or the
// closest enclosing one (`lighting.sun.radiance[1]` → `lighting.sun.radiance`, `stop` → the
// stop fieldset's first field).
function showFieldError(field, message) {
  const all = [...document.querySelectorAll('#bake-form [data-field]')];
  let target = null, f = field;
  while (f && !target) {
    target = all.find(el => el.dataset.field === f) || all.find(el => el.dataset.field.startsWith(f + '.'));
    const up = f.replace(/(\[\d+\]|\.[^.[\]]+)$/, '');
    f = up === f ? '' : up;
  }
  if (!target) { $('form-error').textContent = `${field}: ${message}`; return; }
  target.classList.add('invalid');
  const input = target.matches('input,select') ? target : target.querySelector('input,select');
  if (input) { input.setAttribute('aria-invalid', 'true'); input.focus(); }
  const msg = document.createElement('div');
  msg.className = 'field-error';
  msg.setAttribute('role', 'alert');
  msg.textContent = message;
  target.append(msg);
  if (input) input.setAttribute('aria-describedby', 'field-error-msg');
  msg.id = 'field-error-msg';
  $('form-error').textContent = `The server refused the job: ${field} is invalid.`;
}

$('bake-form').addEventListener('submit', async e => {
  e.preventDefault();
  clearFieldErrors();
  if (!$('f-scene').value) { showFieldError('scene', 'upload a scene first'); return; }
  const btn = $('submit');
  btn.disabled = true;
  try {
    const r = await json('/v1/jobs', {method: 'POST', headers: {'Content-Type': 'application/json'}, body: JSON.stringify(buildBody())});
    // Accepted, with what the server thinks was probably not meant (no light, a faint sun).
    $('form-warning').textContent = (r.warnings || []).map(w => `Queued, but ${w}.`).join(' ');
    await refreshJobs();
    openJob(r.id);
  } catch (err) {
    if (err.status === 422 && err.problem.field) showFieldError(err.problem.field, err.problem.detail);
    else if (err.status !== 401) $('form-error').textContent = `${err.status}: ${err.message}`;
  } finally { btn.disabled = false; }
});

// --- jobs list -------------------------------------------------------------------------------
async function refreshJobs() {
  const {jobs} = await json('/v1/jobs?limit=20');
  $('job-rows').innerHTML = jobs.map(j => {
    const p = j.progress || {fraction: 0, error: null};
    return `<tr data-job="${esc(j.id)}" tabindex="0" class="${state.job?.id === j.id ? 'current' : ''}"><td class="mono">${esc(j.id.slice(0, 8))}</td>` +
      `<td><span class="badge ${esc(j.status)}">${esc(j.status)}</span></td><td>${esc(j.spec.technique)}</td>` +
      `<td><div class="bar"><div style="width:${(p.fraction * 100).toFixed(0)}%"></div></div></td>` +
      `<td>${p.error == null ? '' : (p.error * 100).toFixed(2) + ' %'}</td><td class="hint">${esc(j.created_at.slice(11, 19))}</td></tr>`;
  }).join('') || '<tr><td colspan="6" class="hint">No jobs yet.</td></tr>';
  refreshReferences().catch(() => {});
}
// The reference choices: the caller's succeeded jobs of the scene picked in the form (the
// server checks the rest of what must match and names `reference` in its 422).
async function refreshReferences() {
  const {jobs} = await json('/v1/jobs?status=succeeded&limit=100');
  const sel = $('f-reference'), keep = sel.value, scene = $('f-scene').value;
  const pct = e => e == null ? '' : ` · ${(e * 100).toFixed(2)} %`;
  sel.innerHTML = '<option value="">none</option>' + jobs.filter(j => j.scene === scene).map(j =>
    `<option value="${esc(j.id)}">${esc(j.id.slice(0, 8))} · ${esc(j.spec.technique)} · ${j.spec.resolution}² · ${j.summary?.steps ?? '?'} steps${pct(j.summary?.error?.relative)}</option>`).join('');
  if ([...sel.options].some(o => o.value === keep)) sel.value = keep;
}
$('f-scene').addEventListener('change', () => refreshReferences().catch(() => {}));

$('job-rows').addEventListener('click', e => { const tr = e.target.closest('tr[data-job]'); if (tr) openJob(tr.dataset.job); });
$('job-rows').addEventListener('keydown', e => { const tr = e.target.closest('tr[data-job]'); if (tr && e.key === 'Enter') openJob(tr.dataset.job); });

// --- job page --------------------------------------------------------------------------------
async function openJob(id) {
  if (state.stream) state.stream.abort();
  state.snapshotSeen = 0; state.lightmap = null; state.lightmapKey = null;
  location.hash = 'job=' + id;
  $('job').hidden = false;
  try { showJob(await json('/v1/jobs/' + id)); } catch (err) { $('job-failure').textContent = err.message; return; }
  $('job').focus({preventScroll: true});
  follow(id);
}

// Follows GET /v1/jobs/{id}/events. EventSource cannot send an Authorization header, so the
// stream is read with fetch and parsed here (event: / data: lines, blank line ends an event).
async function follow(id) {
  const ctl = new AbortController();
  state.stream = ctl;
  try {
    const r = await api(`/v1/jobs/${id}/events`, {signal: ctl.signal, headers: {Accept: 'text/event-stream'}});
    const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = '';
    for (;;) {
      const {value, done} = await reader.read();
      if (done) break;
      buf += value;
      let i;
      while ((i = buf.indexOf('\n\n')) >= 0) {
        const block = buf.slice(0, i); buf = buf.slice(i + 2);
        let name = 'message', data = '';
        for (const line of block.split('\n')) {
          if (line.startsWith('event:')) name = line.slice(6).trim();
          else if (line.startsWith('data:')) data += line.slice(5).trimStart();
        }
        if (data) await onEvent(id, name, JSON.parse(data));
      }
    }
  } catch (err) {
    if (err.name === 'AbortError') return;
    // A dropped stream (server restart): poll once, then try again if the job goes on.
    await new Promise(res => setTimeout(res, 2000));
    if (state.stream === ctl && state.job?.id === id && !['succeeded', 'failed', 'cancelled'].includes(state.job.status)) follow(id);
  }
}

async function onEvent(id, name, data) {
  if (state.job?.id !== id) return;
  if (name === 'status' || name === 'done' || name === 'cancelled') showJob(data);
  else if (name === 'failed') showJob(data.job);
  else if (name === 'progress') {
    state.job.progress = data; showProgress(state.job);
    // A split job's task table and a waiting job's reason come with the job's view only.
    if ((state.job.tasks || state.job.waiting_for) && Date.now() - (state.tasksShownAt || 0) > 2000) {
      state.tasksShownAt = Date.now();
      showJob(await json('/v1/jobs/' + id));
    }
  }
  else if (name === 'snapshot') showJob(await json('/v1/jobs/' + id));
  if (name !== 'progress') refreshJobs().catch(() => {});
}

function showProgress(j) {
  const p = j.progress || {steps: 0, fraction: 0, elapsed_s: 0, error: null};
  $('job-bar').style.width = (p.fraction * 100).toFixed(1) + '%';
  // A biased technique's error is bias and noise measured at control texels: say so.
  const last = (j.history || []).at(-1);
  const parts = last && last.bias != null ? ` (bias ${(last.bias * 100).toFixed(2)} %, noise ${(last.noise * 100).toFixed(2)} %)` : '';
  // Light probes are baked after the lightmap (progress.probes, docs/service.md).
  // Against the job's reference (history[].true_error), when it has one.
  const ref = j.plan?.reference;
  const truth = last?.true_error != null ? ` · measured against job ${ref?.job?.slice(0, 8)}: ${(last.true_error * 100).toFixed(2)} %` : '';
  const probes = p.probes ? ` · light probes: step ${p.probes.steps} of ${p.probes.of} (${p.probes.probes} probes)` : '';
  // A long step (CPU path on a large level) says how far it is (progress.step_fraction).
  const within = p.step_fraction != null ? ` (+${(p.step_fraction * 100).toFixed(0)} %)` : '';
  $('job-progress').textContent = `${p.steps} steps${within} · ${p.elapsed_s.toFixed(1)} s` + (p.error == null ? '' : ` · error ${(p.error * 100).toFixed(2)} %${parts}`) + truth + probes;
}

const TERMINAL = ['succeeded', 'failed', 'cancelled'];

function escapeHtml(s) {
  return String(s).replace(/[&<>"']/g, c => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;'})[c]);
}

// Why nobody takes the job (waiting_for), and a split job's tasks (issue 25): each
// task's region, steps of the job, state, worker and own error; the blocklist.
function showTasks(j) {
  const waiting = $('job-waiting');
  waiting.hidden = !j.waiting_for;
  waiting.textContent = j.waiting_for ? 'Waiting for ' + j.waiting_for : '';
  // A job nobody takes sends no events: look again every 5 s while it waits (a worker
  // that meets it may start).
  clearTimeout(state.waitTimer);
  if (j.waiting_for) {
    state.waitTimer = setTimeout(async () => {
      if (state.job?.id !== j.id) return;
      try { showJob(await json('/v1/jobs/' + j.id)); } catch (_) { /* shown at the next event */ }
    }, 5000);
  }
  const box = $('job-tasks');
  box.hidden = !j.tasks;
  if (!j.tasks) return;
  const t = j.tasks;
  const done = t.list.filter(x => x.kind === 'bake' && x.status === 'succeeded').length;
  $('job-tasks-summary').textContent = `${done} of ${t.count} baked` + (t.regions > 1 ? ` · ${t.regions} regions of the grid` : '') + (t.rounds ? ` in ${t.rounds} rounds` : '');
  const cell = v => `<td>${v}</td>`;
  $('job-task-rows').innerHTML = t.list.map(x => `<tr data-task="${x.index}">` + [
    x.kind === 'merge' ? 'merge' : String(x.index),
    x.region == null ? '' : String(x.region) + (x.round == null ? '' : ` · round ${x.round}`),
    x.step_range ? `${x.step_range[0]}–${x.step_range[1]}` : '',
    `<span class="badge ${x.status}">${x.status}</span>`,
    String(x.attempts),
    x.worker ? `<span class="mono">${escapeHtml(x.worker)}</span>` : '',
    x.kind === 'merge' ? '' : `${x.steps} steps`,
    x.error == null ? '' : `${(x.error * 100).toFixed(2)} %`,
    x.wall_s == null ? '' : `${x.wall_s.toFixed(1)} s`,
  ].map(cell).join('') + (x.failure ? `</tr><tr><td></td><td colspan="8" class="error">${escapeHtml(x.failure)}</td>` : '') + '</tr>').join('');
  $('job-blocklist').textContent = t.blocklisted.length
    ? 'Blocklisted for this job: ' + t.blocklisted.map(b => `${b.worker} (${b.failures} failed attempts)`).join(', ')
    : '';
}

function showJob(j) {
  const changed = state.job?.id !== j.id;
  // Views arrive out of order (the cancel request's answer, a snapshot's re-fetch, the
  // event stream's final status): a job never leaves a terminal state, so an older,
  // non-terminal view of the same job is not shown over a terminal one.
  if (!changed && TERMINAL.includes(state.job.status) && !TERMINAL.includes(j.status)) return;
  state.job = j;
  $('job-id').textContent = j.id;
  const st = $('job-status');
  st.textContent = j.status + (j.cancel_requested && j.status === 'running' ? ' (cancelling)' : '');
  st.className = 'badge ' + j.status;
  showProgress(j);
  const finished = ['succeeded', 'failed', 'cancelled'].includes(j.status);
  $('cancel').disabled = finished || j.cancel_requested;
  $('job-failure').textContent = j.failure || '';
  showTasks(j);
  const dl = [];
  if (j.status === 'succeeded') {
    // One link per page (the job's summary lists them) and the manifest; a job stored
    // before pages existed has none listed and its lightmap.exr is its one page.
    const pages = j.summary?.pages || [];
    if (pages.length > 1) {
      for (const p of pages) dl.push(`<a href="/v1/jobs/${j.id}/${p.file}" data-fetch="${j.id}-${p.file}">${p.file}</a>`);
    } else {
      dl.push(`<a href="/v1/jobs/${j.id}/lightmap.exr" data-fetch="${j.id}.exr">lightmap.exr</a>`);
    }
    if (pages.length > 0) dl.push(`<a href="/v1/jobs/${j.id}/lightmaps.json" data-fetch="${j.id}-lightmaps.json">lightmaps.json</a>`);
    dl.push(`<a href="/v1/jobs/${j.id}/preview.png" data-fetch="${j.id}.png">preview.png</a>`);
    // The glTF the lightmap fits: with the UVs the engine made, or the scene's own.
    if (j.summary?.generated_uvs) dl.push(`<a href="/v1/jobs/${j.id}/scene.glb" data-fetch="${j.id}.glb">scene.glb (generated UVs)</a>`);
    else dl.push(`<a href="/v1/scenes/${j.scene}/scene.glb" data-fetch="${j.scene}.glb">scene.glb (its own UVs)</a>`);
    if (j.spec?.probes) dl.push(`<a href="/v1/jobs/${j.id}/probes.json" data-fetch="${j.id}-probes.json">probes.json</a>`);
  } else if (j.snapshots > 0) dl.push(`<a href="/v1/jobs/${j.id}/lightmap.exr?snapshot=latest" data-fetch="${j.id}-snapshot.exr">latest snapshot.exr</a>`);
  dl.push(`<a href="/v1/jobs/${j.id}" data-fetch="${j.id}.json">job.json</a>`);
  $('job-downloads').innerHTML = dl.join('');
  showPlan(j);
  $('job-json').textContent = JSON.stringify(j, null, 2);
  drawPlot(j);
  for (const tr of document.querySelectorAll('#job-rows tr')) tr.classList.toggle('current', tr.dataset.job === j.id);
  if (changed) $('v-note').textContent = '';
  // One view update at a time, in the order the job's states arrived: a snapshot's update
  // still loading the geometry when the end's update set the final lightmap used to finish
  // last and put the snapshot back (the geometry load clears the shown key), so a fast job
  // could end showing a snapshot.
  state.rendering = (state.rendering || Promise.resolve())
    .then(() => updateGeometry(j))
    .then(() => updateLightmap(j))
    .catch(err => { $('v-note').textContent = err.message; });
}

function showPlan(j) {
  const plan = j.summary?.plan || j.plan;
  if (!plan) { $('job-plan').innerHTML = '<p class="hint">The plan is made when a worker starts the job.</p>'; }
  else {
    const items = (list, cls) => (list || []).map(i => `<li class="${cls}"><b>${esc(i.name)}</b>: ${esc(i.why)}</li>`).join('');
    const extra = Object.entries(plan).filter(([k]) => !['passes', 'left_out', 'technique', 'error_estimate', 'validation', 'warnings'].includes(k))
      .map(([k, v]) => `<li>${esc(k)}: <span class="mono">${esc(typeof v === 'object' ? JSON.stringify(v) : v)}</span></li>`).join('');
    const warned = (plan.warnings || []).map(w => `<li class="warn">${esc(w)}</li>`).join('');
    $('job-plan').innerHTML = `<ul class="plan">${warned}${items(plan.passes, 'ran')}${items(plan.left_out, 'left')}${extra}</ul>` +
      (plan.error_estimate ? `<p class="hint">Error estimate: ${esc(plan.error_estimate)}</p>` : '');
  }
  const v = j.summary?.validation || j.summary?.texel_validation || j.plan?.validation || j.plan?.texels;
  if (!v) { $('job-validation').innerHTML = '<p class="hint">The texel validation report comes with the texel set.</p>'; return; }
  const rows = [['valid texels', v.valid_texels], ['inside geometry (removed)', v.inside_geometry_texels], ['overlapping charts', v.overlapping_texels],
    ['partly covered (dilated)', v.partially_covered_texels], ['density spread (max/min)', v.density_spread?.toFixed?.(2)], ['texel set', v.texel_set_bytes != null ? fmtBytes(v.texel_set_bytes) : undefined]]
    .filter(([, x]) => x !== undefined);
  const dens = (v.density || []).map(d => `<tr><td>${esc(d.mesh)}</td><td>${esc(d.texels_per_metre.toFixed(1))} texels/m</td></tr>`).join('');
  $('job-validation').innerHTML = '<table class="report">' + rows.map(([k, x]) => `<tr><th scope="row">${esc(k)}</th><td>${esc(x)}</td></tr>`).join('') + '</table>' +
    (dens ? `<details><summary>Texel density per mesh</summary><table class="report">${dens}</table></details>` : '') +
    ((v.warnings || []).length ? '<ul>' + v.warnings.map(w => `<li class="warn">${esc(w)}</li>`).join('') + '</ul>' : '');
}

$('cancel').addEventListener('click', async () => {
  const j = state.job;
  if (!j) return;
  try { showJob(await json(`/v1/jobs/${j.id}/cancel`, {method: 'POST'})); }
  catch (err) { $('job-failure').textContent = err.message; }
});

// --- error plot: log-log, estimate per snapshot, dashed target ---------------------------------
function drawPlot(j) {
  const pts = (j.history || []).filter(p => p.error > 0 && p.seconds > 0);
  // Measured against the job's reference (orange), and that reference's own error (dotted).
  const truth = (j.history || []).filter(p => p.true_error > 0 && p.seconds > 0);
  const floor = j.plan?.reference?.error;
  const target = j.spec.stop?.target_error;
  const W = 256, H = 180, L = 34, B = 22, T = 8, R = 8;
  if (!pts.length && !truth.length) { $('plot').innerHTML = `<svg viewBox="0 0 ${W} ${H}"><text x="${W / 2}" y="${H / 2}" text-anchor="middle">no error estimate yet</text></svg>`; return; }
  const xs = [...pts, ...truth].map(p => Math.log10(p.seconds)), ys = pts.map(p => Math.log10(p.error));
  for (const p of truth) ys.push(Math.log10(p.true_error));
  if (truth.length && floor > 0) ys.push(Math.log10(floor));
  if (target > 0) ys.push(Math.log10(target));
  for (const p of pts) if (p.noise > 0) ys.push(Math.log10(p.noise));
  let x0 = Math.floor(Math.min(...xs)), x1 = Math.ceil(Math.max(...xs)), y0 = Math.floor(Math.min(...ys)), y1 = Math.ceil(Math.max(...ys));
  if (x1 === x0) x1++; if (y1 === y0) y1++;
  const X = v => L + (v - x0) / (x1 - x0) * (W - L - R), Y = v => H - B - (v - y0) / (y1 - y0) * (H - B - T);
  const label = e => e >= 0 ? String(10 ** e) : (10 ** e).toPrecision(1);
  let s = `<svg viewBox="0 0 ${W} ${H}">`;
  for (let e = x0; e <= x1; e++) s += `<line x1="${X(e)}" x2="${X(e)}" y1="${T}" y2="${H - B}" stroke="#333"/><text x="${X(e)}" y="${H - 8}" text-anchor="middle">${label(e)} s</text>`;
  for (let e = y0; e <= y1; e++) s += `<line x1="${L}" x2="${W - R}" y1="${Y(e)}" y2="${Y(e)}" stroke="#333"/><text x="${L - 3}" y="${Y(e) + 3}" text-anchor="end">${label(e + 2)}%</text>`;
  if (target > 0) s += `<line x1="${L}" x2="${W - R}" y1="${Y(Math.log10(target))}" y2="${Y(Math.log10(target))}" stroke="#f0b849" stroke-dasharray="4 3"/>`;
  // The noise part alone (grey, dashed) under a biased technique's total.
  const noisy = pts.filter(p => p.noise > 0);
  if (noisy.length) s += `<polyline fill="none" stroke="#999" stroke-dasharray="3 2" stroke-width="1" points="${noisy.map(p => `${X(Math.log10(p.seconds)).toFixed(1)},${Y(Math.log10(p.noise)).toFixed(1)}`).join(' ')}"/>`;
  if (truth.length) {
    if (floor > 0) s += `<line class="reference-floor" x1="${L}" x2="${W - R}" y1="${Y(Math.log10(floor))}" y2="${Y(Math.log10(floor))}" stroke="#ff9f6b" stroke-dasharray="1 3"/>`;
    s += `<polyline class="true-error" fill="none" stroke="#ff9f6b" stroke-width="1.5" points="${truth.map(p => `${X(Math.log10(p.seconds)).toFixed(1)},${Y(Math.log10(p.true_error)).toFixed(1)}`).join(' ')}"/>`;
    s += truth.map(p => `<rect class="true-error" x="${(X(Math.log10(p.seconds)) - 2.5).toFixed(1)}" y="${(Y(Math.log10(p.true_error)) - 2.5).toFixed(1)}" width="5" height="5" fill="#ff9f6b"/>`).join('');
  }
  s += `<polyline fill="none" stroke="#7cc4ff" stroke-width="1.5" points="${pts.map(p => `${X(Math.log10(p.seconds)).toFixed(1)},${Y(Math.log10(p.error)).toFixed(1)}`).join(' ')}"/>`;
  s += pts.map(p => `<circle cx="${X(Math.log10(p.seconds)).toFixed(1)}" cy="${Y(Math.log10(p.error)).toFixed(1)}" r="2.5" fill="#7cc4ff"/>`).join('');
  $('plot').innerHTML = s + '</svg>';
}

// --- lightmap: 2D texels and the 3D view --------------------------------------------------------
// binary16 → float, once for all 65536 values.
const HALF = (() => {
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 31, m = h & 1023;
    t[h] = e === 0 ? s * m * 2 ** -24 : e === 31 ? (m ? NaN : s * Infinity) : s * (1 + m / 1024) * 2 ** (e - 15);
  }
  return t;
})();

async function updateGeometry(j) {
  if (!state.viewer) return;
  // The lightmap fits the scene's own TEXCOORD_1, or the UVs the engine generated: their .glb
  // is stored once they are made (the job's plan then names it), before most snapshots.
  const scene = state.scenes.find(s => s.id === j.scene) || await json('/v1/scenes/' + j.scene).catch(() => null);
  const own = scene?.report?.has_lightmap_uvs;
  const generated = j.plan?.generated_scene || (j.status === 'succeeded' && j.summary?.generated_uvs ? `/v1/jobs/${j.id}/scene.glb` : null);
  const src = generated || (own !== false ? `/v1/scenes/${j.scene}/scene.glb` : null);
  if (!src) { $('v-note').textContent = 'This scene gets generated lightmap UVs: the 3D view shows the lightmap once they are made.'; return; }
  if (state.geometryFor === src) return;
  state.geometryFor = src;
  const buf = await (await api(src)).arrayBuffer();
  await state.viewer.load(buf);
  state.lightmapKey = null;
}

async function updateLightmap(j) {
  if (j.snapshots === 0 && j.status !== 'succeeded') { drawLightmap2d(); return; }
  const key = `${j.id}/${j.status === 'succeeded' ? 'final' : j.snapshots}`;
  if (state.lightmapKey === key) return;
  state.lightmapKey = key;
  const r = await api(`/v1/jobs/${j.id}/lightmap.rgba16f` + (j.status === 'succeeded' ? '' : '?snapshot=latest'));
  const w = +r.headers.get('x-lightmap-width'), h = +r.headers.get('x-lightmap-height');
  const halves = new Uint16Array(await r.arrayBuffer());
  state.lightmap = {w, h, halves, label: j.status === 'succeeded' ? 'final lightmap' : `snapshot ${j.snapshots}`};
  if (state.viewer && state.geometryFor) state.viewer.setLightmap(w, h, halves);
  drawLightmap2d();
  await updateProbes(j);
}

// A finished job's light probes, as spheres in the 3D view (shaded by their SH).
async function updateProbes(j) {
  if (!state.viewer || !state.geometryFor) return;
  if (j.status !== 'succeeded' || !j.spec?.probes) { state.viewer.setProbes(null); return; }
  const set = await json(`/v1/jobs/${j.id}/probes.json`).catch(() => null);
  const shown = state.viewer.setProbes(set);
  if (set) $('v-note').textContent = `${shown} light probes shown (of ${set.probes.length}; ${set.probes.filter(p => !p.valid).length} inside geometry), error ${set.error == null ? 'not known yet (one step)' : (100 * set.error).toFixed(2) + ' %'}.`;
}

function drawLightmap2d() {
  const cv = $('lightmap2d'), lm = state.lightmap;
  const g = cv.getContext('2d');
  if (!lm) { g.clearRect(0, 0, cv.width, cv.height); $('lightmap-caption').textContent = 'No snapshot yet.'; return; }
  cv.width = lm.w; cv.height = lm.h;
  const img = g.createImageData(lm.w, lm.h), k = 2 ** Number($('v-exposure').value);
  const srgb = v => { v = Math.min(1, Math.max(0, v * k)); return 255 * (v <= 0.0031308 ? 12.92 * v : 1.055 * v ** (1 / 2.4) - 0.055); };
  for (let i = 0; i < lm.w * lm.h; i++) {
    for (let c = 0; c < 3; c++) img.data[4 * i + c] = srgb(HALF[lm.halves[4 * i + c]]);
    img.data[4 * i + 3] = 255;
  }
  g.putImageData(img, 0, 0);
  // Several pages lie one under another in the grid (W x W each, docs/conventions.md).
  const pages = lm.h > lm.w && lm.h % lm.w === 0 ? ` · ${lm.h / lm.w} pages of ${lm.w}×${lm.w}` : '';
  $('lightmap-caption').textContent = `${lm.label} · ${lm.w}×${lm.h} texels${pages}`;
}

$('v-exposure').addEventListener('input', e => {
  $('v-exposure-out').textContent = `${e.target.value} EV`;
  state.viewer?.setExposure(Number(e.target.value));
  drawLightmap2d();
});
$('v-mode').addEventListener('change', e => state.viewer?.setMode(e.target.value === 'lightmap'));
$('v-filter').addEventListener('change', e => state.viewer?.setFilter(e.target.value === 'nearest'));
$('v-reset').addEventListener('click', () => state.viewer?.resetView());

// --- start -----------------------------------------------------------------------------------
function fmtBytes(n) { return n < 1024 ? n + ' B' : n < 1 << 20 ? (n / 1024).toFixed(1) + ' KiB' : (n / 1048576).toFixed(1) + ' MiB'; }

async function start() {
  try {
    const h = await (await fetch('/healthz')).json();
    $('health').textContent = `v${h.version} · ${h.workers} worker(s)`;
  } catch { $('health').textContent = 'server unreachable'; }
  try {
    await loadTechniques();
    await loadScenes();
    await refreshJobs();
  } catch (err) { if (err.status !== 401) $('form-error').textContent = err.message; return; }
  const m = location.hash.match(/job=([\w-]+)/);
  if (m) openJob(m[1]);
}

try { state.viewer = new Viewer($('view3d')); }
catch (err) { $('v-note').textContent = 'No 3D view: ' + err.message; }
drawDial();
start();
setInterval(() => { if (!$('login').hidden) return; refreshJobs().catch(() => {}); }, 5000);
window.lightmapdConsole = state;  // for the browser test and for debugging

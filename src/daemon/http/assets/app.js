// clearview preview page: sessions, before/after, provenance, views, mask painting.
// Live through server-sent events; no framework, nothing loaded from elsewhere.
'use strict';

const params = new URLSearchParams(location.search);
let token = params.get('token') || sessionStorage.getItem('clearview-token') || '';
if (params.get('token')) {
  sessionStorage.setItem('clearview-token', token);
  params.delete('token');
  const rest = params.toString();
  history.replaceState(null, '', location.pathname + (rest ? '?' + rest : '') + location.hash);
}

const $ = (id) => document.getElementById(id);
let current = decodeURIComponent(location.hash.slice(1)) || null;
let snapshot = null;
let painting = false;
// Served by `clearview collect --http`: results only, no mask painting or keyframe choice.
let readOnly = false;

// A URL of ours with the token (images and the event stream cannot send headers).
function url(path, extra) {
  const u = new URL(path, location.origin);
  if (token) u.searchParams.set('token', token);
  for (const [k, v] of Object.entries(extra || {})) u.searchParams.set(k, v);
  return u.pathname + u.search;
}

async function api(path, options) {
  const o = Object.assign({}, options || {});
  o.headers = Object.assign({}, o.headers || {});
  if (token) o.headers.Authorization = 'Bearer ' + token;
  const r = await fetch(path, o);
  const text = await r.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch (e) { body = { error: text }; }
  if (!r.ok) throw new Error((body && body.error) || r.status + ' ' + r.statusText);
  return body;
}

const sessionPath = (id) => '/api/sessions/' + encodeURIComponent(id);

async function loadSessions() {
  const list = await api('/api/sessions');
  readOnly = !!list.read_only;
  $('paint-toggle').hidden = readOnly;
  const nav = $('sessions');
  if (!list.sessions.length) return;
  nav.replaceChildren(...list.sessions.map((s) => {
    const b = document.createElement('button');
    b.type = 'button';
    b.dataset.id = s.id;
    b.className = s.id === current ? 'current' : '';
    const cov = s.coverage == null ? 'no result yet' : 'result #' + s.result + ' · ' + Math.round(100 * s.coverage) + '% from views';
    b.append(s.id);
    const small = document.createElement('small');
    small.textContent = s.accepted + ' accepted, ' + s.rejected + ' rejected · ' + cov;
    b.append(small);
    b.onclick = () => select(s.id);
    return b;
  }));
  if (!current || !list.sessions.some((s) => s.id === current)) select(list.sessions[0].id);
}

function select(id) {
  if (painting) togglePaint(false);
  current = id;
  history.replaceState(null, '', location.pathname + location.search + '#' + encodeURIComponent(id));
  for (const b of $('sessions').querySelectorAll('button')) b.className = b.dataset.id === id ? 'current' : '';
  loadSession();
}

async function loadSession() {
  if (!current) return;
  const s = await api(sessionPath(current));
  snapshot = s;
  $('main').hidden = false;
  $('title').textContent = s.id;
  const n = s.result ? s.result.number : null;
  const parts = ['keyframe ' + (s.keyframe || '(none yet)'), 'mask ' + (s.mask || '(none: paint one)')];
  if (n != null) parts.push('result #' + n + ' · ' + Math.round(100 * s.coverage) + '% of ' + s.result.masked + ' masked px from views');
  $('summary').textContent = parts.join(' · ');
  const viewer = $('viewer');
  if (s.keyframe) $('before').src = url(sessionPath(s.id) + '/keyframe', { k: s.keyframe });
  const after = $('after');
  if (n != null) {
    after.hidden = false;
    after.src = url(sessionPath(s.id) + '/result', { n: n });
  } else {
    after.hidden = true;
  }
  viewer.dataset.result = n == null ? '' : String(n);
  const prov = $('prov');
  if (s.legend.length) prov.src = url(sessionPath(s.id) + '/provenance', { n: n });
  prov.hidden = !($('show-prov').checked && s.legend.length);
  $('legend').hidden = prov.hidden;
  $('legend').replaceChildren(...s.legend.filter((l) => l.value !== 0).map((l) => {
    const li = document.createElement('li');
    const sw = document.createElement('i');
    sw.style.background = l.colour;
    li.append(sw, l.source + ' (' + l.pixels + ' px)');
    return li;
  }));
  renderSurfaces(s, n);
  renderViews(s);
}

// The surface overlay's colours, as `daemon::provenance::SURFACE_PALETTE` paints them.
const SURFACE_PALETTE = ['#e6194b', '#3cb44b', '#4363d8', '#f58231', '#911eb4', '#42d4f4'];

// Which surface each masked pixel was copied through (the result's `surfaces.png`, drawn
// by the API), with a legend from the result's `planes`: the wall, and each surface off it.
function renderSurfaces(s, n) {
  const surf = $('surf');
  const r = s.result;
  const planes = r && r.surfaces && r.planes ? r.planes : null;
  surf.hidden = !($('show-surf').checked && planes);
  // Drawn by the server from the map at each request: asked for only when shown.
  if (!surf.hidden) surf.src = url(sessionPath(s.id) + '/surfaces', { n: n });
  const legend = $('surf-legend');
  legend.hidden = surf.hidden;
  if (!planes) { legend.replaceChildren(); return; }
  const through = planes.surfaces.map((p) => p.filled_pixels);
  const entries = [['#80808060', 'the wall', r.masked - through.reduce((a, b) => a + b, 0)]];
  through.forEach((px, k) => entries.push([SURFACE_PALETTE[k % SURFACE_PALETTE.length], 'surface ' + (k + 1) + ' off the wall', px]));
  legend.replaceChildren(...entries.map(([colour, what, px]) => {
    const li = document.createElement('li');
    const sw = document.createElement('i');
    sw.style.background = colour;
    li.append(sw, what + ' (' + px + ' px)');
    return li;
  }));
}

function renderViews(s) {
  $('views').replaceChildren(...s.views.map((v) => {
    const card = document.createElement('figure');
    card.className = 'view';
    card.style.margin = '0';
    const img = document.createElement('img');
    img.loading = 'lazy';
    img.alt = v.file;
    img.src = url(sessionPath(s.id) + '/views/' + encodeURIComponent(v.file) + '/thumb');
    const d = document.createElement('div');
    const name = document.createElement('b');
    name.textContent = v.file;
    name.title = v.file;
    const st = document.createElement('span');
    st.className = 'status ' + v.status;
    st.textContent = v.status.replace('_', ' ');
    d.append(name, st);
    if (v.filled != null) d.append(' ' + v.filled + ' px');
    if (v.reason) {
      const r = document.createElement('div');
      r.className = 'reason';
      r.textContent = v.reason;
      d.append(r);
    }
    const q = document.createElement('div');
    q.className = 'reason';
    q.textContent = v.inliers + '/' + v.matches + ' inliers' + (v.median_residual_px != null ? ', ' + v.median_residual_px.toFixed(2) + ' px' : '');
    d.append(q);
    if (!readOnly) {
      const b = document.createElement('button');
      b.type = 'button';
      b.textContent = 'Make keyframe';
      b.onclick = () => chooseKeyframe(v.file);
      d.append(b);
    }
    card.append(img, d);
    return card;
  }));
}

async function chooseKeyframe(file) {
  if (!confirm('Make ' + file + ' the keyframe? It is renamed key.<ext> in the inbox; the mask must be painted again.')) return;
  try {
    await api(sessionPath(current) + '/keyframe', { method: 'PUT', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ file }) });
    say('keyframe chosen: the service is re-aligning the views');
  } catch (e) { say('could not choose the keyframe: ' + e.message); }
}

function say(text) { $('message').textContent = text; }

// Before/after slider: the keyframe shows left of the divider, the result right of it.
function slide() {
  const v = Number($('slider').value);
  $('after').style.clipPath = 'inset(0 0 0 ' + v + '%)';
  $('divider').style.left = v + '%';
}

// ---- mask painting ----
const canvas = $('paint');
const ctx = canvas.getContext('2d');
let last = null;

async function togglePaint(on) {
  painting = on;
  $('viewer').classList.toggle('painting', on);
  canvas.hidden = !on;
  $('paint-controls').hidden = !on;
  $('paint-toggle').textContent = on ? 'Stop painting' : 'Paint mask';
  if (!on) return;
  const key = $('before');
  if (!key.complete) await new Promise((r) => key.addEventListener('load', r, { once: true }));
  canvas.width = key.naturalWidth;
  canvas.height = key.naturalHeight;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (snapshot && snapshot.mask) {
    // Start from the current mask: its white pixels shown red.
    try {
      const m = new Image();
      m.src = url(sessionPath(current) + '/mask', { r: snapshot.revision });
      await m.decode();
      const off = document.createElement('canvas');
      off.width = canvas.width; off.height = canvas.height;
      const o = off.getContext('2d');
      o.drawImage(m, 0, 0, off.width, off.height);
      const d = o.getImageData(0, 0, off.width, off.height);
      for (let i = 0; i < d.data.length; i += 4) {
        const on = d.data[i] > 127;
        d.data[i] = 255; d.data[i + 1] = 0; d.data[i + 2] = 0; d.data[i + 3] = on ? 255 : 0;
      }
      ctx.putImageData(d, 0, 0);
    } catch (e) { /* no mask yet */ }
  }
  say('paint over what should go; save when done');
}

function point(e) {
  const r = canvas.getBoundingClientRect();
  return { x: (e.clientX - r.left) * canvas.width / r.width, y: (e.clientY - r.top) * canvas.height / r.height, s: canvas.width / r.width };
}

function stroke(a, b) {
  ctx.globalCompositeOperation = $('erase').checked ? 'destination-out' : 'source-over';
  ctx.strokeStyle = ctx.fillStyle = '#ff0000';
  ctx.lineCap = ctx.lineJoin = 'round';
  ctx.lineWidth = Number($('brush').value) * b.s;
  ctx.beginPath();
  ctx.moveTo(a.x, a.y);
  ctx.lineTo(b.x + 0.01, b.y);
  ctx.stroke();
}

canvas.addEventListener('pointerdown', (e) => { canvas.setPointerCapture(e.pointerId); last = point(e); stroke(last, last); e.preventDefault(); });
canvas.addEventListener('pointermove', (e) => { if (!last) return; const p = point(e); stroke(last, p); last = p; e.preventDefault(); });
for (const ev of ['pointerup', 'pointercancel']) canvas.addEventListener(ev, () => { last = null; });

async function saveMask() {
  const out = document.createElement('canvas');
  out.width = canvas.width; out.height = canvas.height;
  const o = out.getContext('2d');
  const src = ctx.getImageData(0, 0, canvas.width, canvas.height);
  const dst = o.createImageData(canvas.width, canvas.height);
  let painted = 0;
  for (let i = 0; i < src.data.length; i += 4) {
    const on = src.data[i + 3] > 127 ? 255 : 0;
    painted += on ? 1 : 0;
    dst.data[i] = dst.data[i + 1] = dst.data[i + 2] = on; dst.data[i + 3] = 255;
  }
  o.putImageData(dst, 0, 0);
  const blob = await new Promise((r) => out.toBlob(r, 'image/png'));
  try {
    await api(sessionPath(current) + '/mask', { method: 'PUT', headers: { 'Content-Type': 'image/png' }, body: blob });
    say('mask saved (' + painted + ' px): re-inpainting…');
    togglePaint(false);
  } catch (e) { say('could not save the mask: ' + e.message); }
}

// ---- live updates ----
let pending = null;
function refresh() {
  clearTimeout(pending);
  pending = setTimeout(() => { loadSessions().catch(() => {}); loadSession().catch(() => {}); }, 150);
}

function listen() {
  const es = new EventSource(url('/api/events'));
  es.addEventListener('hello', () => { $('live').textContent = 'live'; $('live').className = 'badge on'; refresh(); });
  es.addEventListener('session', refresh);
  es.addEventListener('result', (e) => {
    const u = JSON.parse(e.data);
    if (u.session === current && !painting) say('new result #' + u.result);
    refresh();
  });
  es.onerror = () => { $('live').textContent = 'reconnecting'; $('live').className = 'badge off'; };
}

$('slider').addEventListener('input', slide);
$('show-prov').addEventListener('change', () => loadSession());
$('show-surf').addEventListener('change', () => loadSession());
$('paint-toggle').addEventListener('click', () => togglePaint(!painting));
$('clear').addEventListener('click', () => ctx.clearRect(0, 0, canvas.width, canvas.height));
$('save').addEventListener('click', saveMask);
slide();
loadSessions().catch((e) => say(e.message));
listen();

// ---- 1:1 zoom with panning (mouse and touch) ----
// Every layer (keyframe, result, provenance, surfaces, paint canvas) is shown at its natural size and
// moved by the same offset inside the viewer, whose height is kept; the before/after
// divider stays where the slider puts it. Self-contained: it only adds listeners.
const zoom = { on: false, x: 0, y: 0, drag: null };

function zoomApply() {
  const viewer = $('viewer');
  const key = $('before');
  const layers = ['before', 'after', 'prov', 'surf', 'paint'].map($);
  if (!zoom.on || !key.naturalWidth) {
    viewer.classList.remove('zoomed');
    viewer.style.height = '';
    for (const el of layers) { el.style.width = ''; el.style.maxWidth = ''; el.style.transform = ''; }
    $('zoom').setAttribute('aria-pressed', 'false');
    slide();
    return;
  }
  viewer.classList.add('zoomed');
  $('zoom').setAttribute('aria-pressed', 'true');
  const w = key.naturalWidth, h = key.naturalHeight;
  const vw = viewer.clientWidth, vh = viewer.clientHeight;
  // Larger than the viewer: kept covering it; smaller: centred.
  zoom.x = w <= vw ? (vw - w) / 2 : Math.min(0, Math.max(vw - w, zoom.x));
  zoom.y = h <= vh ? (vh - h) / 2 : Math.min(0, Math.max(vh - h, zoom.y));
  for (const el of layers) {
    el.style.width = w + 'px';
    el.style.maxWidth = 'none';
    el.style.transform = 'translate(' + zoom.x + 'px, ' + zoom.y + 'px)';
  }
  const cut = Math.max(0, (Number($('slider').value) / 100) * vw - zoom.x);
  $('after').style.clipPath = 'inset(0px 0px 0px ' + cut + 'px)';
}

// Turns 1:1 on or off; on, the image point under viewer position (px, py) stays put.
function zoomToggle(px, py) {
  const viewer = $('viewer');
  const key = $('before');
  if (!key.naturalWidth) return;
  if (!zoom.on) {
    const r = viewer.getBoundingClientRect();
    const fx = px === undefined ? r.width / 2 : px, fy = py === undefined ? r.height / 2 : py;
    const s = key.naturalWidth / key.getBoundingClientRect().width;
    viewer.style.height = r.height + 'px';
    zoom.x = fx - fx * s;
    zoom.y = fy - fy * s;
  }
  zoom.on = !zoom.on;
  zoomApply();
}

const viewerEl = $('viewer');
viewerEl.addEventListener('pointerdown', (e) => {
  if (!zoom.on || painting) return;
  viewerEl.setPointerCapture(e.pointerId);
  zoom.drag = { id: e.pointerId, x: e.clientX, y: e.clientY };
  e.preventDefault();
});
viewerEl.addEventListener('pointermove', (e) => {
  if (!zoom.drag || zoom.drag.id !== e.pointerId) return;
  zoom.x += e.clientX - zoom.drag.x;
  zoom.y += e.clientY - zoom.drag.y;
  zoom.drag.x = e.clientX;
  zoom.drag.y = e.clientY;
  zoomApply();
  e.preventDefault();
});
for (const ev of ['pointerup', 'pointercancel']) viewerEl.addEventListener(ev, () => { zoom.drag = null; });
viewerEl.addEventListener('dblclick', (e) => {
  if (painting) return;
  const r = viewerEl.getBoundingClientRect();
  zoomToggle(e.clientX - r.left, e.clientY - r.top);
});
$('zoom').addEventListener('click', () => zoomToggle());
$('slider').addEventListener('input', () => { if (zoom.on) zoomApply(); });
window.addEventListener('resize', () => { if (zoom.on) zoomApply(); });
$('before').addEventListener('load', () => { if (zoom.on) zoomApply(); });

// muster's web console: plain DOM, no framework, no inline script (the page's
// Content-Security-Policy allows none). Everything a system names is shown with
// textContent, never as HTML.
'use strict';

const $ = (id) => document.getElementById(id);
const HISTORY = 300; // points kept per session for its plot

let me = null;   // {user, operator, csrf}
let ws = null;
let retry = null;
const state = {
  list: { generation: 0, services: [] },
  sessions: new Map(), // session id (string) -> {session, service, kind, payload, link, last, history}
  pending: new Map(),  // req -> {req, service, position}
  links: new Map(),    // link -> {link, data, command, up, forwarded}
  brokerUp: false,
  map: null,      // {width, height, resolution, origin, image}
  world: null,    // the newest world frame
  frames: [],     // arrival times of world frames, for the frame rate shown
  status: null,   // the broker's status (operators)
};

function el(tag, props, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(props || {})) {
    if (k === 'class') e.className = v;
    else if (k === 'data') for (const [dk, dv] of Object.entries(v)) e.dataset[dk] = dv;
    else if (k.startsWith('on')) e.addEventListener(k.slice(2), v);
    else e[k] = v;
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}

function log(text, bad) {
  const li = el('li', { class: bad ? 'bad' : '' }, new Date().toLocaleTimeString() + '  ' + text);
  $('log').prepend(li);
  while ($('log').children.length > 50) $('log').lastChild.remove();
}

// ---- sign-in ----

async function start() {
  $('signin-form').addEventListener('submit', signIn);
  $('signout').addEventListener('click', signOut);
  $('link-form').addEventListener('submit', (e) => {
    e.preventDefault();
    send({ op: 'link', data: $('link-data').value, command: $('link-command').value });
  });
  $('map').addEventListener('click', mapClick);
  setInterval(() => { if (me && me.operator && ws && ws.readyState === WebSocket.OPEN) send({ op: 'status' }); }, 1000);
  const r = await fetch('/api/me', { credentials: 'same-origin' });
  if (r.ok) signedIn(await r.json()); else showSignIn('');
}

function showSignIn(msg) {
  me = null;
  if (ws) { ws.onclose = null; ws.close(); ws = null; }
  $('console').hidden = true;
  $('signout').hidden = true;
  $('who').textContent = '';
  $('broker').textContent = '';
  $('signin').hidden = false;
  $('signin-error').textContent = msg;
}

async function signIn(e) {
  e.preventDefault();
  const body = JSON.stringify({ user: $('signin-user').value, token: $('signin-token').value });
  const r = await fetch('/api/login', {
    method: 'POST', credentials: 'same-origin',
    headers: { 'Content-Type': 'application/json' }, body,
  });
  const j = await r.json().catch(() => ({}));
  if (!r.ok) { $('signin-error').textContent = j.error || ('sign-in failed: ' + r.status); return; }
  $('signin-token').value = '';
  signedIn(j);
}

async function signOut() {
  await fetch('/api/logout', {
    method: 'POST', credentials: 'same-origin',
    headers: { 'Content-Type': 'application/json', 'X-CSRF-Token': me ? me.csrf : '' },
  });
  showSignIn('signed out');
}

function signedIn(m) {
  me = m;
  $('signin').hidden = true;
  $('console').hidden = false;
  $('signout').hidden = false;
  $('who').textContent = m.user + (m.operator ? ' (operator)' : '');
  $('operator').hidden = !m.operator;
  connect();
}

// ---- the socket ----

function connect() {
  clearTimeout(retry);
  const proto = location.protocol === 'https:' ? 'wss://' : 'ws://';
  ws = new WebSocket(proto + location.host + '/ws');
  ws.onmessage = (ev) => onFrame(JSON.parse(ev.data));
  ws.onopen = () => ws.send(JSON.stringify({ op: 'map', on: true }));
  ws.onclose = () => {
    ws = null;
    setBroker(false, 'disconnected');
    if (me) retry = setTimeout(reconnect, 1000);
  };
}

async function reconnect() {
  const r = await fetch('/api/me', { credentials: 'same-origin' }).catch(() => null);
  if (r && r.ok) { me = await r.json(); connect(); }
  else if (r && r.status === 401) showSignIn('signed out');
  else retry = setTimeout(reconnect, 1000);
}

function send(obj) {
  if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(obj));
  else log('not connected: try again in a moment', true);
}

function setBroker(up, text) {
  state.brokerUp = up;
  const b = $('broker');
  b.textContent = text || (up ? 'broker up' : 'broker lost');
  b.className = 'badge ' + (up ? 'up' : 'down');
}

function onFrame(f) {
  switch (f.t) {
    case 'state':
      state.list = f.list || { generation: 0, services: [] };
      state.sessions.clear();
      for (const s of f.sessions) state.sessions.set(s.session, { ...s, history: [] });
      state.pending.clear();
      for (const p of f.pending) state.pending.set(p.req, p);
      state.links.clear();
      for (const l of f.links) state.links.set(l.link, l);
      setBroker(f.broker_up);
      renderList(); renderLinks(); renderSessions();
      for (const s of state.sessions.values()) if (s.last) showLast(s);
      break;
    case 'broker': setBroker(f.up); break;
    case 'list': state.list = f.list; renderList(); renderLinks(); break;
    case 'list_delta': {
      const byId = new Map(state.list.services.map((s) => [s.id, s]));
      for (const id of f.removed) byId.delete(id);
      for (const s of f.set) byId.set(s.id, s);
      state.list = { generation: f.generation, services: [...byId.values()].sort((a, b) => (a.id < b.id ? -1 : a.id > b.id ? 1 : 0)) };
      renderList(); renderLinks();
      break;
    }
    case 'pending':
      state.pending.set(f.req, f);
      if (f.position > 0) log(f.service + ': queued, position ' + f.position);
      renderList();
      break;
    case 'cancelled': state.pending.delete(f.req); renderList(); break;
    case 'refused':
      state.pending.delete(f.req);
      log(f.service + ': refused: ' + f.reason, true);
      renderList();
      break;
    case 'granted':
      state.pending.delete(f.req);
      state.sessions.set(f.session, { ...f, history: [] });
      log(f.service + ': granted');
      renderList(); renderSessions();
      break;
    case 'update':
    case 'status': {
      const s = state.sessions.get(f.session);
      if (!s) break;
      s.last = f;
      showLast(s);
      break;
    }
    case 'ended':
      state.sessions.delete(f.session);
      log(f.service + ': session ended: ' + f.reason);
      renderSessions(); renderList();
      break;
    case 'link': state.links.set(f.link.link, f.link); renderLinks(); break;
    case 'link_up': { const l = state.links.get(f.link); if (l) { l.up = true; renderLinks(); } break; }
    case 'forwarded': { const l = state.links.get(f.link); if (l) { l.forwarded += 1; renderLinks(); } break; }
    case 'link_ended': state.links.delete(f.link); log('link ' + f.link + ' ended: ' + f.reason); renderLinks(); break;
    case 'link_refused': log('link refused: ' + f.error, true); break;
    case 'input_refused': log('input refused: ' + f.error, true); break;
    case 'operated':
      if (f.status) { state.status = f.status; renderOperator(); break; }
      log((f.what || 'operation') + (f.ok ? ': done' : ': refused: ' + f.error), !f.ok);
      break;
    case 'map': setMap(f); break;
    case 'world':
      state.world = f;
      state.frames.push(performance.now());
      if (state.frames.length > 30) state.frames.shift();
      requestAnimationFrame(drawMap);
      break;
    case 'error': log(f.error, true); break;
    case 'closed': if (f.reason === 'signed out') showSignIn('signed out'); break;
  }
}

// ---- rendering ----

function renderList() {
  const tbody = $('services').querySelector('tbody');
  tbody.replaceChildren();
  $('generation').textContent = 'generation ' + state.list.generation;
  const waiting = new Map();
  for (const p of state.pending.values()) waiting.set(p.service, p);
  for (const s of state.list.services) {
    const p = waiting.get(s.id);
    let action;
    if (p) {
      action = el('span', {},
        el('span', { class: 'waiting' }, p.position > 0 ? 'queued #' + p.position + ' ' : 'asking… '),
        el('button', { onclick: () => send({ op: 'cancel', req: p.req }) }, 'Cancel'));
    } else {
      action = el('button', { class: 'request', disabled: s.withdrawn, onclick: () => send({ op: 'request', service: s.id }) }, 'Request');
    }
    if (me && me.operator && !s.remote) {
      const op = s.withdrawn ? 'restore' : 'withdraw';
      action = el('span', {}, action, ' ',
        el('button', { class: op, onclick: () => send({ op, service: s.id }) }, s.withdrawn ? 'Restore' : 'Withdraw'));
    }
    const tr = el('tr', { class: s.withdrawn ? 'withdrawn' : '', data: { service: s.id } },
      el('td', { class: 'id', title: s.description }, s.id),
      el('td', {}, s.kind),
      el('td', {}, s.payload),
      el('td', { class: 'in-use' }, s.in_use + '/' + s.quota),
      el('td', { class: 'queued' }, s.queue ? String(s.queued) : '–'),
      el('td', {}, s.host || 'here'),
      el('td', {}, action));
    tbody.append(tr);
  }
}

function renderLinks() {
  const fill = (sel, kind) => {
    const keep = sel.value;
    sel.replaceChildren(...state.list.services.filter((s) => s.kind === kind)
      .map((s) => el('option', { value: s.id }, s.id)));
    if ([...sel.options].some((o) => o.value === keep)) sel.value = keep;
  };
  fill($('link-data'), 'data');
  fill($('link-command'), 'command');
  const ul = $('links');
  ul.replaceChildren(...[...state.links.values()].map((l) =>
    el('li', { data: { link: String(l.link) } },
      l.data + ' → ' + l.command + ' ',
      el('span', { class: 'link-state' }, l.up ? 'up, ' + l.forwarded + ' forwarded' : 'asking…'), ' ',
      el('button', { onclick: () => send({ op: 'unlink', link: l.link }) }, 'Unlink'))));
}

function renderSessions() {
  renderGoalTargets();
  const box = $('sessions');
  const have = new Set();
  for (const card of [...box.children]) {
    if (!state.sessions.has(card.dataset.session)) card.remove(); else have.add(card.dataset.session);
  }
  for (const s of state.sessions.values()) {
    if (have.has(s.session)) continue;
    const end = el('button', { class: 'end', onclick: () => send({ op: 'end', session: s.session }) }, 'End');
    const card = el('div', { class: 'session ' + s.kind, data: { session: s.session, service: s.service } },
      el('strong', {}, s.service), ' ', el('span', { class: 'dim' }, s.kind + ', ' + s.payload + (s.link ? ', link ' + s.link : '')), ' ', end);
    if (s.kind === 'data') {
      card.append(el('div', { class: 'value' }, 'no value yet'), el('canvas', { width: 260, height: 130 }));
    } else {
      const x = el('input', { type: 'number', step: 'any', placeholder: 'x', class: 'goal-x', size: 5 });
      const y = el('input', { type: 'number', step: 'any', placeholder: 'y', class: 'goal-y', size: 5 });
      const form = el('form', { class: 'goal' }, 'goal ', x, ' ', y, ' ', el('button', { type: 'submit' }, 'Set goal'));
      form.addEventListener('submit', (e) => {
        e.preventDefault();
        send({ op: 'goal', session: s.session, x: Number(x.value), y: Number(y.value) });
      });
      card.append(form, el('div', { class: 'status' }, 'no status yet'));
    }
    box.append(card);
  }
}

function renderGoalTargets() {
  const sel = $('goal-target');
  const keep = sel.value;
  const cmds = [...state.sessions.values()].filter((s) => s.kind === 'command' && s.payload === 'goal2d');
  sel.replaceChildren(...(cmds.length
    ? cmds.map((s) => el('option', { value: s.session }, s.service))
    : [el('option', { value: '' }, '(request a goal2d command service first)')]));
  if ([...sel.options].some((o) => o.value === keep)) sel.value = keep;
}

// ---- the floor ----

const COLOURS = { red: '#e53935', green: '#43a047', blue: '#1e88e5', yellow: '#fdd835', magenta: '#d81b60', cyan: '#00acc1' };

function setMap(f) {
  const img = document.createElement('canvas');
  img.width = f.width; img.height = f.height;
  const g = img.getContext('2d');
  g.fillStyle = '#fff'; g.fillRect(0, 0, f.width, f.height);
  g.fillStyle = '#37474f';
  for (let k = 0; k + 2 < f.runs.length; k += 3) {
    const [j, i, n] = [f.runs[k], f.runs[k + 1], f.runs[k + 2]];
    g.fillRect(i, f.height - 1 - j, n, 1); // row 0 is the bottom (y up)
  }
  state.map = { ...f, image: img };
  const c = $('map');
  c.height = Math.round(c.width * f.height / f.width);
  drawMap();
}

// World metres -> canvas pixels, and back.
function scale() { const m = state.map; return $('map').width / (m.width * m.resolution); }
function toPx(x, y) {
  const m = state.map, k = scale();
  return [(x - m.origin[0]) * k, $('map').height - (y - m.origin[1]) * k];
}
function toWorld(px, py) {
  const m = state.map, k = scale();
  return [m.origin[0] + px / k, m.origin[1] + ($('map').height - py) / k];
}

function drawMap() {
  const m = state.map;
  if (!m) return;
  const c = $('map'), g = c.getContext('2d');
  g.imageSmoothingEnabled = false;
  g.drawImage(m.image, 0, 0, c.width, c.height);
  const w = state.world;
  if (!w) return;
  const k = scale();
  for (const p of w.plans) {
    g.strokeStyle = '#fb8c00'; g.lineWidth = 2; g.setLineDash([6, 4]);
    g.beginPath();
    const pts = p.path.length ? p.path : [p.goal];
    const r = w.robots.find((r) => r.name === p.robot);
    if (r) g.moveTo(...toPx(r.x, r.y)); else g.moveTo(...toPx(...pts[0]));
    for (const q of pts) g.lineTo(...toPx(q[0], q[1]));
    g.stroke(); g.setLineDash([]);
  }
  for (const p of w.people) {
    const [x, y] = toPx(p.x, p.y);
    g.fillStyle = COLOURS[p.colour] || '#999';
    g.beginPath(); g.arc(x, y, Math.max(4, 0.25 * k), 0, 2 * Math.PI); g.fill();
  }
  for (const t of w.tracks) {
    const [x, y] = toPx(t.x, t.y);
    g.strokeStyle = COLOURS[t.colour] || '#555'; g.lineWidth = 2;
    if (t.lost) g.setLineDash([3, 3]);
    g.beginPath(); g.arc(x, y, Math.max(9, (t.sigma || 0) * k), 0, 2 * Math.PI); g.stroke();
    g.setLineDash([]);
  }
  g.font = '12px system-ui, sans-serif';
  for (const r of w.robots) {
    const [x, y] = toPx(r.x, r.y), s = Math.max(7, 0.35 * k);
    g.save(); g.translate(x, y); g.rotate(-r.theta);
    g.fillStyle = r.name.startsWith('D') ? '#ef6c00' : '#616161';
    g.beginPath(); g.moveTo(s, 0); g.lineTo(-s * 0.7, s * 0.6); g.lineTo(-s * 0.7, -s * 0.6); g.closePath(); g.fill();
    g.restore();
    g.fillStyle = '#1b1f24'; g.fillText(r.name, x + s, y - s);
  }
  $('map-time').textContent = 'sim ' + w.time.toFixed(1) + ' s';
  const fr = state.frames;
  if (fr.length > 1) $('map-fps').textContent = ((fr.length - 1) * 1000 / (fr[fr.length - 1] - fr[0])).toFixed(0) + ' frames/s';
}

function mapClick(ev) {
  if (!state.map) return;
  const c = $('map'), r = c.getBoundingClientRect();
  const px = (ev.clientX - r.left) * c.width / r.width, py = (ev.clientY - r.top) * c.height / r.height;
  const [x, y] = toWorld(px, py);
  const session = $('goal-target').value;
  if (!session) { log('request a goal2d command service first, then click its goal', true); return; }
  send({ op: 'goal', session, x, y });
  log('goal (' + x.toFixed(2) + ', ' + y.toFixed(2) + ') sent to ' + state.sessions.get(session).service);
}

// ---- operators ----

function renderOperator() {
  const st = state.status;
  if (!st) return;
  $('op-sessions').querySelector('tbody').replaceChildren(...st.sessions.map((s) =>
    el('tr', { data: { session: String(s.session), user: s.user } },
      el('td', {}, String(s.session)), el('td', {}, s.service), el('td', {}, s.user),
      el('td', {}, el('button', { class: 'op-end', onclick: () => send({ op: 'end_session', session: String(s.session) }) }, 'End')))));
  $('op-users').querySelector('tbody').replaceChildren(...st.users.map((u) =>
    el('tr', { data: { user: u.user } },
      el('td', {}, u.user), el('td', {}, String(u.pid)), el('td', {}, String(u.links.length)),
      el('td', {}, el('button', { class: 'op-drop', onclick: () => send({ op: 'drop_user', user: u.user }) }, 'Revoke')))));
}

function fmt(v) {
  if (v === null || typeof v !== 'object') return String(v);
  return Object.entries(v).filter(([k]) => k !== 'type')
    .map(([k, x]) => k + ' ' + (typeof x === 'number' ? x.toFixed(2) : (typeof x === 'object' ? JSON.stringify(x) : String(x))))
    .join('  ');
}

function showLast(s) {
  const card = $('sessions').querySelector('[data-session="' + s.session + '"]');
  if (!card) return;
  const f = s.last;
  if (f.t === 'status') {
    card.querySelector('.status').textContent = f.state + (f.detail ? ': ' + f.detail : '');
    return;
  }
  card.querySelector('.value').textContent = '#' + f.seq + (f.gap ? ' (gap ' + f.gap + ')' : '') + '  ' + fmt(f.value);
  const v = f.value || {};
  if (typeof v.x === 'number' && typeof v.y === 'number') s.history.push([v.x, v.y]);
  else if (typeof v.value === 'number') s.history.push([f.seq, v.value]);
  if (s.history.length > HISTORY) s.history.shift();
  plot(card.querySelector('canvas'), s.history);
}

function plot(canvas, pts) {
  if (!canvas || pts.length === 0) return;
  const g = canvas.getContext('2d');
  g.clearRect(0, 0, canvas.width, canvas.height);
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of pts) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
  const span = Math.max(x1 - x0, y1 - y0, 1e-6);
  const sx = (canvas.width - 10) / span, sy = (canvas.height - 10) / span;
  const k = Math.min(sx, sy);
  g.strokeStyle = '#1565c0';
  g.beginPath();
  pts.forEach(([x, y], i) => {
    const px = 5 + (x - x0) * k, py = canvas.height - 5 - (y - y0) * k;
    if (i === 0) g.moveTo(px, py); else g.lineTo(px, py);
  });
  g.stroke();
  const [lx, ly] = pts[pts.length - 1];
  g.fillStyle = '#c62828';
  g.beginPath();
  g.arc(5 + (lx - x0) * k, canvas.height - 5 - (ly - y0) * k, 3, 0, 2 * Math.PI);
  g.fill();
}

document.addEventListener('DOMContentLoaded', start);

// Live map page of the uavmm fusion server: polls the REST API about once a second and draws on a canvas,
// in Web-Mercator (the tile grid of DESIGN.md 3): joint heatmap PNG tiles, UAV footprints and headings,
// fused objects and global tracks with their ids. No libraries, no network beyond this server.
// What is drawn is also written to the DOM (#summary data-* attributes, #uav-list, #track-list) for tests.
'use strict';

(() => {
  const TILE_PX = 256;
  const GRID_Z = 18;          // zoom of the shared grid: the server renders these tiles without resampling
  const MIN_ZOOM = 3, MAX_ZOOM = 22;
  const POLL_MS = 1000;
  const FETCH_TIMEOUT_MS = 4000;
  const UAV_COLORS = ['#1f6fd1', '#d1372f', '#1d9a4a', '#8a45c4', '#e07b00', '#0f9fb0', '#a0522d', '#d43f9a'];

  const $ = (id) => document.getElementById(id);
  const canvas = $('canvas');
  const ctx = canvas.getContext('2d');
  const mapEl = $('map');
  const summary = $('summary');

  const state = {
    // view: centre in normalised Web-Mercator (0..1 east, 0..1 south) and a fractional zoom
    view: { mx: 0.5, my: 0.5, zoom: 3 },
    userMoved: false,     // the user panned or zoomed: the view no longer fits itself to the data
    fittedUavs: 0,        // UAVs with a position at the last automatic fit
    cls: null,
    classes: [],
    uavs: [],
    tracks: [],
    objects: [],
    jointIndex: [],       // [{cls, z, x, y, seq, max}] of the selected class
    tiles: new Map(),     // "cls/z/x/y" -> {img, version, loadingVersion}
    wanted: new Map(),    // "cls/z/x/y" -> {cls, z, x, y, version}: the tiles to draw at the current zoom
    drawnTiles: 0,
    updates: 0,
    liveTracks: [],       // the tracks of the last poll
    replay: null,         // {t, tracks}: the time slider shows the tracks at t (timeline.js); null = live
    status: 'starting',
    cursor: null,         // last cursor position in canvas pixels
  };

  // ---------------------------------------------------------------------------------------- projection
  function project(lat, lon) {
    const s = Math.sin(Math.max(-85.0511, Math.min(85.0511, lat)) * Math.PI / 180);
    return [(lon + 180) / 360, 0.5 - Math.log((1 + s) / (1 - s)) / (4 * Math.PI)];
  }

  function unproject(mx, my) {
    const lon = mx * 360 - 180;
    const lat = Math.atan(Math.sinh(Math.PI * (1 - 2 * my))) * 180 / Math.PI;
    return [lat, lon];
  }

  function worldPx() { return TILE_PX * Math.pow(2, state.view.zoom); }

  function size() { return [canvas.clientWidth, canvas.clientHeight]; }

  function toScreen(lat, lon) {
    const [mx, my] = project(lat, lon);
    const [w, h] = size();
    const k = worldPx();
    return [(mx - state.view.mx) * k + w / 2, (my - state.view.my) * k + h / 2];
  }

  function toLatLon(px, py) {
    const [w, h] = size();
    const k = worldPx();
    return unproject(state.view.mx + (px - w / 2) / k, state.view.my + (py - h / 2) / k);
  }

  function metresPerPixel() {
    const [lat] = unproject(state.view.mx, state.view.my);
    return 40075016.686 * Math.cos(lat * Math.PI / 180) / worldPx();
  }

  // ---------------------------------------------------------------------------------------- colours
  function hash(text) {
    let h = 2166136261;
    for (let i = 0; i < text.length; i++) { h ^= text.charCodeAt(i); h = Math.imul(h, 16777619); }
    return h >>> 0;
  }

  function uavColor(id) { return UAV_COLORS[hash(String(id)) % UAV_COLORS.length]; }

  function trackColor(gid) { return `hsl(${(gid * 137.508) % 360}, 75%, 38%)`; }

  // ---------------------------------------------------------------------------------------- data
  // A server bound beyond loopback needs a bearer token (docs/fusion.md): open the page as .../#token=TOKEN.
  // The token is kept for this tab (sessionStorage) and taken out of the address bar; the fragment never
  // reaches the server or its logs. Requests send it as Authorization, tile images as access_token.
  const token = (() => {
    const match = /(?:^#|&)token=([^&]+)/.exec(window.location.hash);
    if (match) {
      const value = decodeURIComponent(match[1]);
      try { sessionStorage.setItem('uavmm-token', value); } catch (e) { /* storage off: this load only */ }
      history.replaceState(null, '', window.location.pathname + window.location.search);
      return value;
    }
    try { return sessionStorage.getItem('uavmm-token'); } catch (e) { return null; }
  })();
  const authHeaders = token ? { Authorization: `Bearer ${token}` } : {};
  const tokenQuery = token ? `&access_token=${encodeURIComponent(token)}` : '';

  async function getJson(path) {
    const ctrl = new AbortController();
    const timer = setTimeout(() => ctrl.abort(), FETCH_TIMEOUT_MS);
    try {
      const response = await fetch(path, { signal: ctrl.signal, cache: 'no-store', headers: authHeaders });
      if (!response.ok) {
        const error = new Error(`${path}: HTTP ${response.status}`);
        error.status = response.status;
        throw error;
      }
      return await response.json();
    } finally {
      clearTimeout(timer);
    }
  }

  async function poll() {
    try {
      const health = await getJson('/healthz');
      updateClasses(health.classes || []);
      const cls = state.cls;
      const minScore = Math.max(0, Math.min(1, parseFloat($('min-score').value) || 0));
      const [uavs, tracks, objects, index] = await Promise.all([
        getJson('/v1/uavs'),
        getJson('/v1/tracks'),
        cls ? getJson(`/v1/objects?cls=${encodeURIComponent(cls)}&min_score=${minScore}`)
          .catch((e) => (e.status === 404 ? { features: [] } : Promise.reject(e)))
          : Promise.resolve({ features: [] }),
        cls ? getJson(`/v1/joint/tiles?cls=${encodeURIComponent(cls)}`) : Promise.resolve([]),
      ]);
      state.uavs = uavs;
      state.liveTracks = tracks.features || [];
      state.tracks = state.replay ? state.replay.tracks : state.liveTracks;  // timeline.js sets replay
      state.objects = objects.features || [];
      state.jointIndex = index;
      state.updates += 1;
      // a gateway of sharded servers says which shards are down: their UAVs and regions are stale
      const down = health.degraded && health.down ? ` · DEGRADED: shard ${health.down.join(', ')} down` : '';
      setStatus('ok', `${health.uavs_online} UAV(s) online${down} · updated ${new Date().toLocaleTimeString()}`);
      // fit the view when a UAV appears, until the user takes over the view
      const placed = uavs.filter((u) => u.state).length;
      if (!state.userMoved && placed > state.fittedUavs && fit()) state.fittedUavs = placed;
      refreshTiles();
      updateLegend();
    } catch (e) {
      if (e.status === 401) {
        setStatus('error', token ? 'the token was refused: open the page with a valid #token=...'
          : 'this server needs a token: open the page as shown by uavmm fusion (.../#token=...)');
      } else {
        setStatus('error', 'server not reachable: retrying');
      }
    }
    draw();
    setTimeout(poll, POLL_MS);
  }

  function setStatus(status, text) {
    state.status = status;
    const el = $('status');
    el.dataset.status = status;
    el.textContent = text;
    summary.dataset.status = status;
  }

  function updateClasses(classes) {
    const select = $('cls');
    if (classes.join() !== state.classes.join()) {
      state.classes = classes;
      select.replaceChildren(...classes.map((c) => new Option(c, c)));
    }
    if (!state.cls || !classes.includes(state.cls)) {
      state.cls = classes.includes('person') ? 'person' : (classes[0] || null);
    }
    if (state.cls) select.value = state.cls;
  }

  // ---------------------------------------------------------------------------------------- heatmap tiles
  function tileZoom() { return Math.max(0, Math.min(GRID_Z, Math.round(state.view.zoom))); }

  // The tiles to show at the current zoom: the parents of the grid's non-empty joint tiles, each with a
  // version (the newest seq of its children) so that a changed tile is fetched again.
  function wantedTiles() {
    const z = tileZoom();
    const shift = GRID_Z - z;
    const wanted = new Map();
    for (const t of state.jointIndex) {
      if (t.z !== GRID_Z || !(t.max > 0)) continue;
      const x = Math.floor(t.x / Math.pow(2, shift)), y = Math.floor(t.y / Math.pow(2, shift));
      const key = `${t.cls}/${z}/${x}/${y}`;
      const prev = wanted.get(key);
      if (!prev || t.seq > prev.version) wanted.set(key, { cls: t.cls, z, x, y, version: t.seq });
    }
    return wanted;
  }

  function refreshTiles() {
    const wanted = wantedTiles();
    for (const [key, t] of wanted) {
      let entry = state.tiles.get(key);
      if (!entry) { entry = { img: null, version: -1, loadingVersion: -1 }; state.tiles.set(key, entry); }
      if (entry.version === t.version || entry.loadingVersion === t.version) continue;
      entry.loadingVersion = t.version;
      const img = new Image();
      img.onload = () => {
        if (t.version >= entry.version) { entry.img = img; entry.version = t.version; }
        scheduleDraw();
      };
      img.onerror = () => { entry.loadingVersion = -1; };
      img.src = `/v1/tiles/${encodeURIComponent(t.cls)}/${t.z}/${t.x}/${t.y}.png?v=${t.version}${tokenQuery}`;
    }
    for (const key of state.tiles.keys()) if (!wanted.has(key)) state.tiles.delete(key);
    state.wanted = wanted;
  }

  // ---------------------------------------------------------------------------------------- drawing
  let drawPending = false;
  function scheduleDraw() {
    if (drawPending) return;
    drawPending = true;
    requestAnimationFrame(() => { drawPending = false; draw(); });
  }

  function resize() {
    const dpr = window.devicePixelRatio || 1;
    const [w, h] = size();
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  }

  function draw() {
    resize();
    const [w, h] = size();
    ctx.clearRect(0, 0, w, h);
    labels.length = 0;
    state.basemapTiles = state.basemap ? state.basemap.draw(ctx, state.view, w, h) : 0;
    drawGrid(w, h);
    state.drawnTiles = $('show-heat').checked ? drawHeat(w, h) : 0;
    if ($('show-footprints').checked) drawFootprints();
    if ($('show-tracks').checked) drawTrackHistories();
    if ($('show-objects').checked) drawObjects();
    state.hiddenLabels = 0;
    drawUavs();
    if ($('show-tracks').checked) drawTracks();
    updateScale();
    updateCursor();
    writeSummary();
  }

  // faint outlines of the grid's z18 tiles (about 100 m) so that the scale of the map is visible
  function drawGrid(w, h) {
    if (state.view.zoom < 14) return;
    const n = Math.pow(2, GRID_Z);
    const k = worldPx();
    const x0 = Math.floor((state.view.mx - w / 2 / k) * n), x1 = Math.ceil((state.view.mx + w / 2 / k) * n);
    const y0 = Math.floor((state.view.my - h / 2 / k) * n), y1 = Math.ceil((state.view.my + h / 2 / k) * n);
    if ((x1 - x0) * (y1 - y0) > 4000) return;
    ctx.save();
    ctx.strokeStyle = 'rgba(60, 70, 60, 0.13)';
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = x0; x <= x1; x++) {
      const sx = Math.round((x / n - state.view.mx) * k + w / 2) + 0.5;
      ctx.moveTo(sx, 0); ctx.lineTo(sx, h);
    }
    for (let y = y0; y <= y1; y++) {
      const sy = Math.round((y / n - state.view.my) * k + h / 2) + 0.5;
      ctx.moveTo(0, sy); ctx.lineTo(w, sy);
    }
    ctx.stroke();
    ctx.restore();
  }

  function drawHeat(w, h) {
    const k = worldPx();
    let drawn = 0;
    ctx.save();
    ctx.globalAlpha = 0.9;
    ctx.imageSmoothingEnabled = state.view.zoom < GRID_Z + 1;
    for (const [key, entry] of state.tiles) {
      if (!entry.img || !state.wanted.has(key)) continue;
      const t = state.wanted.get(key);
      const n = Math.pow(2, t.z);
      const sx = (t.x / n - state.view.mx) * k + w / 2, sy = (t.y / n - state.view.my) * k + h / 2;
      const size = k / n;
      if (sx > w || sy > h || sx + size < 0 || sy + size < 0) continue;
      ctx.drawImage(entry.img, sx, sy, size, size);
      drawn += 1;
    }
    ctx.restore();
    return drawn;
  }

  function path(points) {
    ctx.beginPath();
    points.forEach(([lat, lon], i) => {
      const [x, y] = toScreen(lat, lon);
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
  }

  function drawFootprints() {
    for (const u of state.uavs) {
      const fp = u.state && u.state.footprint;
      if (!fp || fp.length < 3) continue;
      const color = u.online ? uavColor(u.id) : '#8a939d';
      ctx.save();
      path(fp);
      ctx.closePath();
      ctx.globalAlpha = 0.10;
      ctx.fillStyle = color;
      ctx.fill();
      ctx.globalAlpha = 0.85;
      ctx.strokeStyle = color;
      ctx.lineWidth = 1.5;
      if (!u.online) ctx.setLineDash([5, 4]);
      ctx.stroke();
      ctx.restore();
    }
  }

  function drawTrackHistories() {
    ctx.save();
    ctx.lineWidth = 1.5;
    ctx.globalAlpha = 0.55;
    for (const f of state.tracks) {
      const hist = f.properties.history || [];
      if (hist.length < 2) continue;
      ctx.strokeStyle = trackColor(f.properties.gid);
      path(hist.map(([, lat, lon]) => [lat, lon]).concat([[f.geometry.coordinates[1], f.geometry.coordinates[0]]]));
      ctx.stroke();
    }
    ctx.restore();
  }

  function drawObjects() {
    ctx.save();
    ctx.lineWidth = 1.5;
    for (const f of state.objects) {
      const [lon, lat] = f.geometry.coordinates;
      const [x, y] = toScreen(lat, lon);
      const r = 4 + 3 * (f.properties.score || 0);
      ctx.beginPath();
      ctx.moveTo(x, y - r); ctx.lineTo(x + r, y); ctx.lineTo(x, y + r); ctx.lineTo(x - r, y); ctx.closePath();
      ctx.strokeStyle = '#ffffff';
      ctx.lineWidth = 3;
      ctx.stroke();
      ctx.strokeStyle = '#0b6e5a';
      ctx.lineWidth = 1.5;
      ctx.stroke();
    }
    ctx.restore();
  }

  // Labels that would overlap one drawn before them are left out (UAVs are drawn first, then tracks in
  // list order: tracked before lost); the marker is always drawn.
  const labels = [];
  function placeLabel(text, x, y) {
    const width = ctx.measureText(text).width, height = 12;
    const box = [x - 1, y - height / 2 - 1, x + width + 1, y + height / 2 + 1];
    if (labels.some((b) => box[0] < b[2] && b[0] < box[2] && box[1] < b[3] && b[1] < box[3])) return false;
    labels.push(box);
    return true;
  }

  function drawTracks() {
    ctx.save();
    ctx.font = '600 11px system-ui, sans-serif';
    ctx.textBaseline = 'middle';
    const ordered = [...state.tracks].sort((a, b) => (a.properties.status === 'tracked' ? 0 : 1)
      - (b.properties.status === 'tracked' ? 0 : 1));
    for (const f of ordered) {
      const p = f.properties;
      const [lon, lat] = f.geometry.coordinates;
      const [x, y] = toScreen(lat, lon);
      const color = trackColor(p.gid);
      ctx.beginPath();
      ctx.arc(x, y, 4.5, 0, 2 * Math.PI);
      ctx.lineWidth = 2;
      ctx.strokeStyle = '#ffffff';
      ctx.stroke();
      if (p.status === 'tracked') { ctx.fillStyle = color; ctx.fill(); } else { ctx.strokeStyle = color; ctx.stroke(); }
      const label = `#${p.gid}`;
      if (!placeLabel(label, x + 7, y - 7)) { state.hiddenLabels += 1; continue; }
      ctx.lineWidth = 3;
      ctx.strokeStyle = 'rgba(255, 255, 255, 0.9)';
      ctx.strokeText(label, x + 7, y - 7);
      ctx.fillStyle = color;
      ctx.fillText(label, x + 7, y - 7);
    }
    ctx.restore();
  }

  function drawUavs() {
    ctx.save();
    ctx.font = '600 12px system-ui, sans-serif';
    ctx.textBaseline = 'middle';
    for (const u of state.uavs) {
      const s = u.state;
      if (!s) continue;
      const [x, y] = toScreen(s.lat, s.lon);
      const color = u.online ? uavColor(u.id) : '#8a939d';
      ctx.save();
      ctx.translate(x, y);
      ctx.rotate((s.heading_deg || 0) * Math.PI / 180);  // heading clockwise from north = canvas rotation
      ctx.beginPath();
      ctx.moveTo(0, -13); ctx.lineTo(8, 9); ctx.lineTo(0, 4); ctx.lineTo(-8, 9); ctx.closePath();
      ctx.fillStyle = color;
      ctx.strokeStyle = '#ffffff';
      ctx.lineWidth = 2;
      ctx.stroke();
      ctx.fill();
      ctx.restore();
      const label = `${u.id} ${Math.round(s.height_m)} m`;
      if (!placeLabel(label, x + 12, y + 10)) { state.hiddenLabels += 1; continue; }
      ctx.lineWidth = 3;
      ctx.strokeStyle = 'rgba(255, 255, 255, 0.9)';
      ctx.strokeText(label, x + 12, y + 10);
      ctx.fillStyle = color;
      ctx.fillText(label, x + 12, y + 10);
    }
    ctx.restore();
  }

  // ---------------------------------------------------------------------------------------- overlays
  function updateScale() {
    const mpp = metresPerPixel();
    const target = 120 * mpp;
    const p = Math.pow(10, Math.floor(Math.log10(target)));
    const nice = [5, 2, 1].map((m) => m * p).find((v) => v <= target) || p;
    $('scale-bar').style.width = `${Math.round(nice / mpp)}px`;
    $('scale-label').textContent = nice >= 1000 ? `${nice / 1000} km` : `${nice} m`;
    $('scale').dataset.metres = String(nice);
  }

  // lat/lon under the cursor (of the view's centre while the cursor is off the map)
  function updateCursor() {
    const el = $('cursor');
    const [w, h] = size();
    const at = state.cursor || [w / 2, h / 2];
    const [lat, lon] = toLatLon(at[0], at[1]);
    const text = `${Math.abs(lat).toFixed(6)}° ${lat >= 0 ? 'N' : 'S'}, ${Math.abs(lon).toFixed(6)}° ${lon >= 0 ? 'E' : 'W'}`;
    el.textContent = state.cursor ? text : `centre ${text}`;
    el.dataset.lat = lat.toFixed(7);
    el.dataset.lon = lon.toFixed(7);
    el.dataset.source = state.cursor ? 'cursor' : 'centre';
  }

  function writeSummary() {
    const online = state.uavs.filter((u) => u.online).length;
    const d = summary.dataset;
    d.uavs = String(state.uavs.length);
    d.uavsOnline = String(online);
    d.tracks = String(state.tracks.length);
    d.objects = String(state.objects.length);
    d.heatTiles = String(state.drawnTiles);
    d.basemapTiles = String(state.basemapTiles || 0);
    d.hiddenLabels = String(state.hiddenLabels || 0);
    d.cls = state.cls || '';
    d.updates = String(state.updates);
    d.zoom = state.view.zoom.toFixed(2);
    d.replay = state.replay ? String(state.replay.t) : '';
    $('uav-count').textContent = state.uavs.length;
    $('uav-online-count').textContent = online;
    $('track-count').textContent = state.tracks.length;
    $('object-count').textContent = state.objects.length;
    $('tile-count').textContent = state.drawnTiles;
  }

  function updateLegend() {
    const items = state.uavs.map((u) => {
      const li = document.createElement('li');
      li.className = 'uav';
      li.dataset.uav = u.id;
      li.dataset.online = String(Boolean(u.online));
      const swatch = document.createElement('span');
      swatch.className = 'swatch';
      swatch.style.background = u.online ? uavColor(u.id) : '#8a939d';
      const name = document.createElement('span');
      name.className = 'name';
      name.textContent = u.id;
      const detail = document.createElement('div');
      detail.className = 'detail';
      const s = u.state;
      const rates = u.rates || {};
      const parts = [];
      if (s) parts.push(`${s.height_m.toFixed(0)} m, pitch ${s.pitch_deg.toFixed(0)}°, heading ${s.heading_deg.toFixed(0)}°`);
      parts.push(`${(rates.tile || 0).toFixed(0)} tiles/s, ${((u.bytes_per_s || 0) / 1000).toFixed(0)} kB/s`);
      if (u.tiles !== undefined) parts.push(`covers ${u.tiles} tiles`);
      if (u.shard !== undefined && u.shard !== null) parts.push(`shard ${u.shard}${u.degraded ? ' (down: degraded)' : ''}`);
      detail.textContent = parts.join(' · ');
      li.append(swatch, name, detail);
      return li;
    });
    $('uav-list').replaceChildren(...items);
    const tracks = [...state.tracks].sort((a, b) => a.properties.gid - b.properties.gid).map((f) => {
      const p = f.properties;
      const li = document.createElement('li');
      li.dataset.gid = String(p.gid);
      li.dataset.status = p.status;
      li.title = `${p.cls}, score ${Number(p.score).toFixed(2)}, ${p.status}, seen by ` +
        (p.active_members || []).map((m) => m[0]).join(', ');
      const dot = document.createElement('span');
      dot.className = 'dot';
      dot.style.background = trackColor(p.gid);
      li.append(dot, `#${p.gid}`);
      return li;
    });
    $('track-list').replaceChildren(...tracks);
  }

  // ---------------------------------------------------------------------------------------- view changes
  // Fit the UAVs, their footprints and the tracks into the view; false when there is nothing to fit.
  function fit() {
    const pts = [];
    for (const u of state.uavs) {
      if (!u.state) continue;
      pts.push([u.state.lat, u.state.lon]);
      for (const p of u.state.footprint || []) pts.push(p);
    }
    for (const f of state.tracks) pts.push([f.geometry.coordinates[1], f.geometry.coordinates[0]]);
    if (!pts.length) return false;
    const ms = pts.map(([lat, lon]) => project(lat, lon));
    const xs = ms.map((m) => m[0]), ys = ms.map((m) => m[1]);
    const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    const [w, h] = size();
    const span = Math.max((x1 - x0) / Math.max(w - 80, 50), (y1 - y0) / Math.max(h - 80, 50), 1e-12);
    state.view.mx = (x0 + x1) / 2;
    state.view.my = (y0 + y1) / 2;
    state.view.zoom = Math.max(MIN_ZOOM, Math.min(20.5, Math.log2(1 / (span * TILE_PX))));
    refreshTiles();
    return true;
  }

  function zoomAt(px, py, delta) {
    const before = toLatLon(px, py);
    state.view.zoom = Math.max(MIN_ZOOM, Math.min(MAX_ZOOM, state.view.zoom + delta));
    // keep the point under the cursor where it was
    const [mx, my] = project(before[0], before[1]);
    const [w, h] = size();
    const k = worldPx();
    state.view.mx = mx - (px - w / 2) / k;
    state.view.my = my - (py - h / 2) / k;
    state.userMoved = true;
    refreshTiles();
    scheduleDraw();
  }

  function zoomCentre(delta) { const [w, h] = size(); zoomAt(w / 2, h / 2, delta); }

  let drag = null;
  mapEl.addEventListener('pointerdown', (e) => {
    drag = { x: e.clientX, y: e.clientY, mx: state.view.mx, my: state.view.my };
    mapEl.setPointerCapture(e.pointerId);
    mapEl.classList.add('dragging');
  });
  mapEl.addEventListener('pointermove', (e) => {
    const rect = canvas.getBoundingClientRect();
    state.cursor = [e.clientX - rect.left, e.clientY - rect.top];
    if (drag) {
      const k = worldPx();
      state.view.mx = drag.mx - (e.clientX - drag.x) / k;
      state.view.my = drag.my - (e.clientY - drag.y) / k;
      state.userMoved = true;
    }
    scheduleDraw();
  });
  const endDrag = () => { drag = null; mapEl.classList.remove('dragging'); };
  mapEl.addEventListener('pointerup', endDrag);
  mapEl.addEventListener('pointercancel', endDrag);
  mapEl.addEventListener('pointerleave', () => { state.cursor = null; scheduleDraw(); });
  mapEl.addEventListener('wheel', (e) => {
    e.preventDefault();
    const rect = canvas.getBoundingClientRect();
    const step = e.deltaMode === 1 ? e.deltaY / 3 : e.deltaY / 100;
    zoomAt(e.clientX - rect.left, e.clientY - rect.top, -0.5 * Math.max(-2, Math.min(2, step)));
  }, { passive: false });
  mapEl.addEventListener('dblclick', (e) => {
    const rect = canvas.getBoundingClientRect();
    zoomAt(e.clientX - rect.left, e.clientY - rect.top, e.shiftKey ? -1 : 1);
  });
  window.addEventListener('keydown', (e) => {
    if (e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement) return;
    if (e.key === '+' || e.key === '=') zoomCentre(0.5);
    else if (e.key === '-') zoomCentre(-0.5);
    else if (e.key === 'f') { fit(); scheduleDraw(); }
  });
  $('zoom-in').addEventListener('click', () => zoomCentre(1));
  $('zoom-out').addEventListener('click', () => zoomCentre(-1));
  $('fit').addEventListener('click', () => { fit(); scheduleDraw(); });
  $('cls').addEventListener('change', (e) => { state.cls = e.target.value; state.jointIndex = []; refreshTiles(); pollSoon(); });
  for (const id of ['show-heat', 'show-footprints', 'show-objects', 'show-tracks']) {
    $(id).addEventListener('change', scheduleDraw);
  }
  window.addEventListener('resize', scheduleDraw);

  // a class change should not wait for the next poll; the poll loop itself keeps running on its timer
  let soon = null;
  function pollSoon() {
    if (soon) return;
    soon = setTimeout(async () => {
      soon = null;
      const cls = state.cls;
      try {
        state.jointIndex = await getJson(`/v1/joint/tiles?cls=${encodeURIComponent(cls)}`);
        refreshTiles();
      } catch (e) { /* the regular poll reports errors */ }
      scheduleDraw();
    }, 0);
  }

  async function loadBasemap() {
    try {
      const config = await getJson('/v1/basemap.json');
      state.basemap = window.UavmmBasemap(config, tokenQuery, scheduleDraw);
      const el = $('attribution');
      el.textContent = state.basemap.attribution;
      el.hidden = !state.basemap.attribution;
      scheduleDraw();
    } catch (e) { /* 404: no basemap configured */ }
  }

  // details.js, timeline.js, debugging, tests
  window.uavmmMap = { state, fit, project, unproject, toLatLon, toScreen, redraw: () => { updateLegend(); scheduleDraw(); },
                      getJson };
  draw();
  loadBasemap();
  poll();
})();

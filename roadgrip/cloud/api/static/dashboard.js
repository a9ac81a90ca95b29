/* roadgrip live dashboard. roadgrip/cloud/api/dashboard.py describes the routes, where the credentials come from, why the
 * page polls, and the data-* attributes it sets on #dashboard once it has drawn. No build step, no library but Leaflet;
 * the chart is drawn here in SVG. */
(function () {
  'use strict';

  // ColorBrewer RdYlGn, low mu red: [mu, [r, g, b]], linear in between; mu outside 0..1 takes the end colour.
  const STOPS = [[0.0, [165, 0, 38]], [0.2, [215, 48, 39]], [0.4, [253, 174, 97]], [0.6, [254, 224, 139]],
                 [0.8, [102, 189, 99]], [1.0, [26, 152, 80]]];
  const GREY = '#9aa0a6';  // a cell driven without recent evidence about mu: no mu to show
  const AUTH_KEY = 'roadgrip.dashboard.auth';  // sessionStorage: this tab only, gone when it closes
  const GAP_MS = 1000;  // the chart breaks its line where estimates are further apart (the estimator restarted)
  const PAGE = 10000;  // estimates per request (the API's default limit)
  const SVG_NS = 'http://www.w3.org/2000/svg';

  const root = document.getElementById('dashboard');
  const $ = (id) => document.getElementById(id);
  const state = {
    config: null, auth: null, map: null, fitted: false, timer: null, busy: false, again: false,
    vehicle: new URLSearchParams(location.search).get('vehicle'),
    series: [], seriesVehicle: null,  // the chosen vehicle's estimates in the chart, oldest first
    cells: new Map(), warnings: new Map(), vehicles: new Map(), stations: new Map(),  // drawn layers by key
    cellRings: new Map(),  // H3 cell id -> its polygon [[lat, lon], ...], for the warnings' outlines
  };

  // ------------------------------------------------------------------------------------------------ helpers
  function esc(text) {
    return String(text).replace(/[&<>"']/g, (c) => ({'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;',
                                                       "'": '&#39;'}[c]));
  }

  function fmt(x, digits = 2) {
    return x === null || x === undefined ? '-' : Number(x).toFixed(digits);
  }

  function utcTime(ms) {
    return new Date(ms).toISOString().slice(11, 19);
  }

  function muColour(mu) {
    const m = Math.min(1, Math.max(0, mu));
    for (let k = 1; k < STOPS.length; k++) {
      const [m1, c1] = STOPS[k];
      if (m <= m1) {
        const [m0, c0] = STOPS[k - 1];
        const f = (m - m0) / (m1 - m0);
        return `rgb(${c0.map((c, i) => Math.round(c + f * (c1[i] - c))).join(',')})`;
      }
    }
    return `rgb(${STOPS[STOPS.length - 1][1].join(',')})`;
  }

  function setData(values) {
    for (const [name, value] of Object.entries(values)) root.dataset[name] = String(value);
  }

  function setStatus(status, text) {
    setData({status});
    $('status').textContent = text;
    $('status').classList.toggle('error', status !== 'ok');
  }

  // ------------------------------------------------------------------------------------------------ credentials
  function basicHeader(name, secret) {
    const bytes = new TextEncoder().encode(`${name}:${secret}`);
    return 'Basic ' + btoa(String.fromCharCode(...bytes));
  }

  function store(header) {
    state.auth = header;
    try {
      if (header) sessionStorage.setItem(AUTH_KEY, header); else sessionStorage.removeItem(AUTH_KEY);
    } catch (e) { /* storage disabled: this page load keeps them in memory */ }
  }

  function readCredentials() {
    // #name:secret, taken once and removed from the address bar (and so from the history and bookmarks)
    const fragment = decodeURIComponent(location.hash.slice(1));
    const colon = fragment.indexOf(':');
    if (colon > 0) {
      store(basicHeader(fragment.slice(0, colon), fragment.slice(colon + 1)));
      history.replaceState(null, '', location.pathname + location.search);
      return;
    }
    try { state.auth = sessionStorage.getItem(AUTH_KEY); } catch (e) { state.auth = null; }
  }

  function showLogin(message, status) {
    store(null);
    clearTimeout(state.timer);
    $('login').hidden = false;
    $('logout').hidden = true;
    $('login-error').textContent = message;
    setStatus(status, message || 'a reader\'s name and secret are needed');
  }

  function onLogin(event) {
    event.preventDefault();  // never submitted: the secret must not end up in a URL
    const name = event.target.elements.namedItem('name'), secret = event.target.elements.namedItem('secret');
    store(basicHeader(name.value.trim(), secret.value));
    secret.value = '';
    $('login').hidden = true;
    tick();
  }

  // ------------------------------------------------------------------------------------------------ API
  class HttpError extends Error {
    constructor(status, detail) {
      super(`HTTP ${status}${detail ? ': ' + detail : ''}`);
      this.status = status;
    }
  }

  async function api(path) {
    // credentials 'omit': the Authorization header is ours; the browser adds none and shows no login prompt on 401
    const response = await fetch(path, {headers: {Authorization: state.auth, Accept: 'application/json'},
                                        credentials: 'omit', cache: 'no-store'});
    if (!response.ok) {
      let detail = '';
      try { detail = JSON.stringify((await response.json()).detail); } catch (e) { /* not JSON */ }
      throw new HttpError(response.status, detail);
    }
    return response.json();
  }

  // ------------------------------------------------------------------------------------------------ map
  function initMap() {
    const map = L.map('map', {zoomSnap: 0.25}).setView([20, 0], 2);
    for (const [pane, z] of [['cells', 410], ['warnings', 420], ['stations', 425], ['vehicles', 430]]) {
      map.createPane(pane).style.zIndex = String(z);
    }
    if (state.config.map_tiles_url) {
      L.tileLayer(state.config.map_tiles_url, {maxZoom: 19, attribution: state.config.map_tiles_attribution || ''})
        .addTo(map);
    }
    const legend = L.control({position: 'bottomleft'});
    legend.onAdd = () => $('legend');
    legend.addTo(map);
    const bar = document.querySelector('.legend-bar');
    bar.style.background = 'linear-gradient(to right, ' +
      STOPS.map(([m, c]) => `rgb(${c.join(',')}) ${m * 100}%`).join(', ') + ')';
    state.map = map;
  }

  // Draw `items` as layers kept by key: new ones created, present ones updated in place (an open tooltip stays
  // open), vanished ones removed.
  function sync(registry, items, keyOf, create, update) {
    const seen = new Set();
    for (const item of items) {
      const key = keyOf(item);
      seen.add(key);
      let layer = registry.get(key);
      if (!layer) {
        layer = create(item);
        registry.set(key, layer);
        layer.addTo(state.map);
      }
      update(layer, item);
    }
    for (const [key, layer] of registry) {
      if (!seen.has(key)) {
        layer.remove();
        registry.delete(key);
      }
    }
  }

  function drawCells(geojson) {
    const features = geojson.features.filter((f) => f.geometry && f.geometry.type === 'Polygon');
    for (const f of features) {
      state.cellRings.set(f.properties.cell, f.geometry.coordinates[0].map(([lon, lat]) => [lat, lon]));
    }
    sync(state.cells, features, (f) => f.properties.cell,
      (f) => L.polygon(state.cellRings.get(f.properties.cell), {pane: 'cells', weight: 0.6, color: '#3a3f44'})
        .bindTooltip(''),
      (layer, f) => {
        const p = f.properties;
        const measured = p.status === 'measured' && p.mu !== null;
        const bounded = p.status === 'bounded' && p.mu_lower !== null;  // calm passes proved a lower bound only
        layer.setStyle({fillColor: measured ? muColour(p.mu) : bounded ? muColour(p.mu_lower) : GREY,
                        fillOpacity: measured ? 0.72 : bounded ? 0.3 : 0.45, opacity: measured ? 0.6 : 0.35});
        layer.setTooltipContent(
          `<b>cell ${esc(p.cell)}</b><br>` +
          (measured ? `mu ${fmt(p.mu)} (90 %: ${fmt(p.mu_lower)} to ${fmt(p.mu_upper)})`
            : bounded ? `mu at least ${fmt(p.mu_lower)} (90 %), what calm passes proved`
              : 'no recent evidence about mu') +
          (p.n_stations ? `<br>${p.n_stations} roadside station(s)` : '') +
          `<br>${p.n_vehicles} vehicle(s), ${p.n_estimates} estimates, ${p.n_excited} excited` +
          `<br>last ${utcTime(p.last_ms)} UTC`);
      });
    for (const key of state.cellRings.keys()) if (!state.cells.has(key)) state.cellRings.delete(key);
    return {cells: features.length,
            measured: features.filter((f) => f.properties.status === 'measured' && f.properties.mu !== null).length};
  }

  function drawWarnings(warnings) {
    const active = warnings.filter((w) => w.roadgrip && w.roadgrip.status === 'active');
    sync(state.warnings, active, (w) => w.roadgrip.warning_id,
      (w) => {
        const position = w.denm.management.eventPosition;
        const centre = [position.latitude / 1e7, position.longitude / 1e7];  // 0.1 microdegree
        const ring = state.cellRings.get(w.roadgrip.cell);
        const outline = ring ? L.polygon(ring, {pane: 'warnings', color: '#111', weight: 3, dashArray: '6 4',
                                                fill: false, interactive: false})
                             : L.circle(centre, {pane: 'warnings', radius: 40, color: '#111', weight: 3,
                                                 dashArray: '6 4', fill: false, interactive: false});
        const icon = L.marker(centre, {icon: L.divIcon({className: 'warning-icon', html: '!', iconSize: [22, 22]}),
                                       keyboard: false}).bindTooltip('');
        return L.featureGroup([outline, icon]);
      },
      (group, w) => {
        const r = w.roadgrip;
        group.eachLayer((layer) => {
          if (layer instanceof L.Marker) {
            layer.setTooltipContent(`<b>slippery road</b> (cell ${esc(r.cell)})<br>mu upper bound ${fmt(r.mu_upper)}` +
                                    `<br>${r.n_passes} low passes, ${r.n_vehicles} vehicle(s), update ${r.update}`);
          }
        });
      });
    $('warning-count').textContent = `(${active.length})`;
    $('warning-list').replaceChildren(...active.map((w) => {
      const li = document.createElement('li');
      li.textContent = `cell ${w.roadgrip.cell}: mu below ${fmt(w.roadgrip.mu_upper)}, ` +
                       `${w.roadgrip.n_vehicles} vehicle(s), ${w.roadgrip.n_passes} passes`;
      return li;
    }));
    return active.length;
  }

  function drawVehicles(latest) {
    const placed = latest.filter((v) => v.latitude_deg !== null && v.longitude_deg !== null);
    sync(state.vehicles, placed, (v) => v.vehicle_id,
      (v) => L.circleMarker([v.latitude_deg, v.longitude_deg], {pane: 'vehicles', radius: 7})
        .bindTooltip(esc(v.vehicle_id), {permanent: true, direction: 'right', offset: [8, 0],
                                         className: 'vehicle-label'})
        .on('click', () => choose(v.vehicle_id)),
      (layer, v) => {
        const chosen = v.vehicle_id === state.vehicle;
        layer.setLatLng([v.latitude_deg, v.longitude_deg]);
        layer.setRadius(chosen ? 9 : 7);
        layer.setStyle({color: chosen ? '#000' : '#1d2b3a', weight: chosen ? 4 : 2, fillOpacity: 1,
                        fillColor: v.excited ? muColour(v.mu) : '#fff'});
        if (chosen) layer.bringToFront();
      });
    $('vehicle-count').textContent = `(${latest.length})`;
    $('vehicle-list').replaceChildren(...latest.map((v) => {
      const li = document.createElement('li');
      li.classList.toggle('chosen', v.vehicle_id === state.vehicle);
      const swatch = document.createElement('i');
      swatch.className = 'swatch vehicle';
      swatch.style.background = v.excited ? muColour(v.mu) : '#fff';
      const name = document.createElement('span');
      name.textContent = v.vehicle_id;
      const mu = document.createElement('span');
      mu.className = 'mu';
      mu.textContent = `${fmt(v.mu)} [${fmt(v.mu_lower)}, ${fmt(v.mu_upper)}]${v.excited ? '' : ' not excited'}`;
      li.append(swatch, name, mu);
      li.addEventListener('click', () => choose(v.vehicle_id));
      return li;
    }));
    return placed.length;
  }

  // Roadside stations (roadgrip/cloud/fanout/stations.py): a diamond at the station, filled with the colour of the mu its
  // latest report gave (white: no evidence, surface state unknown), dashed once the report is older than STALE_S.
  const STALE_S = 300;  // five missed reports of a station reporting every minute

  function age(seconds) {
    return seconds < 120 ? `${Math.round(seconds)} s` : `${Math.round(seconds / 60)} min`;
  }

  function stationText(s, ageS) {
    const parts = [s.surface_state];
    if (s.surface_temperature_c !== null) parts.push(`${fmt(s.surface_temperature_c, 1)} \u00b0C`);
    if (s.water_film_thickness_mm !== null) parts.push(`film ${fmt(s.water_film_thickness_mm)} mm`);
    if (s.friction !== null) parts.push(`friction ${fmt(s.friction)}`);
    return parts.join(', ') + (s.mu !== null ? `; mu ${fmt(s.mu)} (90 %: ${fmt(s.mu_lower)} to ${fmt(s.mu_upper)})`
                                             : '; no friction evidence') + `; ${age(ageS)} ago`;
  }

  function drawStations(answer) {
    const now = answer.server_time_ms;
    sync(state.stations, answer.stations, (s) => s.station_id,
      (s) => L.marker([s.latitude_deg, s.longitude_deg], {pane: 'stations', keyboard: false,
                                                           icon: L.divIcon({className: 'station-icon', iconSize: [14, 14]})})
        .bindTooltip(''),
      (layer, s) => {
        const ageS = Math.max(0, (now - s.timestamp_ms) / 1000);
        layer.setLatLng([s.latitude_deg, s.longitude_deg]);
        const element = layer.getElement();
        if (element) {
          element.style.background = s.mu !== null ? muColour(s.mu) : '#fff';
          element.classList.toggle('stale', ageS > STALE_S);
        }
        layer.setTooltipContent(`<b>station ${esc(s.station_id)}</b><br>${esc(stationText(s, ageS))}`);
      });
    $('station-count').textContent = `(${answer.stations.length})`;
    $('station-list').replaceChildren(...answer.stations.map((s) => {
      const li = document.createElement('li');
      const swatch = document.createElement('i');
      swatch.className = 'swatch station';
      swatch.style.background = s.mu !== null ? muColour(s.mu) : '#fff';
      const name = document.createElement('span');
      name.textContent = s.station_id;
      const text = document.createElement('span');
      text.className = 'mu';
      text.textContent = stationText(s, Math.max(0, (now - s.timestamp_ms) / 1000));
      li.append(swatch, name, text);
      return li;
    }));
    return answer.stations.length;
  }

  function fitOnce() {
    if (state.fitted) return;
    const bounds = L.latLngBounds([]);
    for (const cell of state.cells.values()) bounds.extend(cell.getBounds());
    for (const vehicle of state.vehicles.values()) bounds.extend(vehicle.getLatLng());
    for (const station of state.stations.values()) bounds.extend(station.getLatLng());
    if (bounds.isValid()) {
      state.map.fitBounds(bounds, {padding: [40, 40], maxZoom: 17, animate: false});
      state.fitted = true;
    }
  }

  // ------------------------------------------------------------------------------------------------ chart
  function choose(vehicleId) {
    if (vehicleId === state.vehicle) return;
    state.vehicle = vehicleId;
    const params = new URLSearchParams(location.search);
    params.set('vehicle', vehicleId);
    history.replaceState(null, '', `${location.pathname}?${params}`);
    tick();
  }

  async function refreshChart(latest) {
    const id = state.vehicle;
    if (state.seriesVehicle !== id) {
      state.series = [];
      state.seriesVehicle = id;
    }
    const newest = latest.find((v) => v.vehicle_id === id);
    const windowMs = state.config.chart_window_s * 1000;
    if (newest) {
      // only what is newer than the chart's last point: a few rows a second, not the whole window each time (a
      // vehicle's estimates are stored in time order: the pipeline never estimates a sample that comes too late)
      const series = state.series;
      let start = series.length ? series[series.length - 1].timestamp_ms + 1
                                : Math.max(0, newest.timestamp_ms - windowMs);
      while (start <= newest.timestamp_ms) {
        const page = (await api(`/v1/vehicles/${encodeURIComponent(id)}/estimates?start_ms=${start}&limit=${PAGE}`))
          .estimates;
        if (id !== state.vehicle) return;  // another vehicle was chosen meanwhile; the next round draws it
        series.push(...page);
        if (page.length < PAGE) break;
        start = page[page.length - 1].timestamp_ms + 1;
      }
      const cutoff = series.length ? series[series.length - 1].timestamp_ms - windowMs : 0;
      state.series = series.filter((p) => p.timestamp_ms >= cutoff);
    }
    drawChart();
  }

  function svg(parent, tag, attrs, text) {
    const node = document.createElementNS(SVG_NS, tag);
    for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
    if (text !== undefined) node.textContent = text;
    parent.appendChild(node);
    return node;
  }

  function drawChart() {
    const chart = $('chart');
    const points = state.vehicle === state.seriesVehicle ? state.series : [];
    $('chart-title').textContent = state.vehicle || '(click a vehicle)';
    setData({chartVehicle: state.vehicle || '', chartPoints: points.length});
    chart.replaceChildren();
    const W = chart.clientWidth || 340, H = chart.clientHeight || 220;
    chart.setAttribute('viewBox', `0 0 ${W} ${H}`);
    if (!points.length) {
      svg(chart, 'text', {x: W / 2, y: H / 2, 'text-anchor': 'middle', class: 'empty'},
          state.vehicle ? `no estimates of ${state.vehicle} yet` : 'click a vehicle on the map or in the list');
      return;
    }
    const pad = {left: 32, right: 8, top: 8, bottom: 30};
    const t0 = points[0].timestamp_ms, t1 = Math.max(points[points.length - 1].timestamp_ms, t0 + 10000);
    const top = Math.min(2, Math.max(1, Math.ceil(Math.max(...points.map((p) => p.mu_upper)) * 5) / 5));
    const x = (t) => pad.left + (t - t0) / (t1 - t0) * (W - pad.left - pad.right);
    const y = (mu) => pad.top + (1 - Math.min(top, Math.max(0, mu)) / top) * (H - pad.top - pad.bottom);
    for (let m = 0; m <= top + 1e-9; m += 0.2) {
      svg(chart, 'line', {x1: pad.left, x2: W - pad.right, y1: y(m), y2: y(m), class: 'grid'});
      svg(chart, 'text', {x: pad.left - 4, y: y(m) + 3, 'text-anchor': 'end'}, m.toFixed(1));
    }
    for (let k = 0; k <= 3; k++) {
      const t = t0 + k / 3 * (t1 - t0);
      svg(chart, 'text', {x: x(t), y: H - pad.bottom + 14, 'text-anchor': k === 0 ? 'start' : k === 3 ? 'end' : 'middle'},
          utcTime(t));
    }
    svg(chart, 'text', {x: W - pad.right, y: H - 3, 'text-anchor': 'end'}, 'time (UTC)');
    svg(chart, 'line', {x1: pad.left, x2: pad.left, y1: pad.top, y2: H - pad.bottom, class: 'axis'});
    svg(chart, 'line', {x1: pad.left, x2: W - pad.right, y1: H - pad.bottom, y2: H - pad.bottom, class: 'axis'});
    // one band and one line per run of estimates without a gap
    let band = '', line = '', excited = '';
    let start = 0;
    for (let k = 1; k <= points.length; k++) {
      if (k < points.length && points[k].timestamp_ms - points[k - 1].timestamp_ms <= GAP_MS) continue;
      const run = points.slice(start, k);
      band += 'M' + run.map((p) => `${x(p.timestamp_ms).toFixed(1)},${y(p.mu_upper).toFixed(1)}`).join('L') +
              'L' + [...run].reverse().map((p) => `${x(p.timestamp_ms).toFixed(1)},${y(p.mu_lower).toFixed(1)}`)
                .join('L') + 'Z';
      line += 'M' + run.map((p) => `${x(p.timestamp_ms).toFixed(1)},${y(p.mu).toFixed(1)}`).join('L');
      start = k;
    }
    for (const p of points) {
      if (p.excited) excited += `M${x(p.timestamp_ms).toFixed(1)},${H - pad.bottom}v-6`;
    }
    svg(chart, 'path', {d: band, class: 'band'});
    svg(chart, 'path', {d: line, class: 'line'});
    if (excited) svg(chart, 'path', {d: excited, class: 'excited'});
    const threshold = state.config.warning_threshold_mu;
    svg(chart, 'line', {x1: pad.left, x2: W - pad.right, y1: y(threshold), y2: y(threshold), class: 'threshold'});
  }

  // ------------------------------------------------------------------------------------------------ the loop
  async function refresh() {
    const [geojson, warnings, latest, stations] = await Promise.all([
      api('/v1/map'), api('/v1/warnings'), api('/v1/vehicles/latest'), api('/v1/stations')]);
    const cells = drawCells(geojson);
    const nWarnings = drawWarnings(warnings.warnings);
    if (!state.vehicle && latest.vehicles.length) state.vehicle = latest.vehicles[0].vehicle_id;
    const nVehicles = drawVehicles(latest.vehicles);
    const nStations = drawStations(stations);
    fitOnce();
    await refreshChart(latest.vehicles);
    const dataUntil = Math.max(0, ...latest.vehicles.map((v) => v.timestamp_ms));
    setData({cells: cells.cells, cellsMeasured: cells.measured, warnings: nWarnings, vehicles: nVehicles,
             stations: nStations, updated: Date.now()});
    setStatus('ok', `live: ${cells.cells} cells (${cells.measured} with mu), ${nWarnings} warning(s), ` +
                    `${latest.vehicles.length} vehicle(s), ${nStations} station(s)` +
                    (dataUntil ? `; newest estimate ${new Date(dataUntil).toISOString().slice(0, 19)} UTC` : ''));
  }

  async function tick() {
    if (state.busy) {  // a round is running: run another as soon as it ends
      state.again = true;
      return;
    }
    clearTimeout(state.timer);
    if (!state.auth) {
      showLogin('', 'login');
      return;
    }
    state.busy = true;
    $('logout').hidden = false;
    try {
      if (!document.hidden) await refresh();  // a hidden tab keeps its timer but asks nothing
    } catch (err) {
      if (err instanceof HttpError && err.status === 401) {
        showLogin('name or secret refused', 'unauthorized');
      } else if (err instanceof HttpError && err.status === 403) {
        showLogin('this credential may not read the map: use a reader\'s', 'forbidden');
      } else if (err instanceof HttpError) {
        setStatus('error', `the service answered ${err.message}: retrying`);
      } else {
        setStatus('unreachable', `cannot reach the service (${err.message}): retrying`);
      }
    } finally {
      state.busy = false;
      if (state.auth) state.timer = setTimeout(tick, state.again ? 0 : state.config.refresh_interval_s * 1000);
      state.again = false;
    }
  }

  function start() {
    $('login').addEventListener('submit', onLogin);
    $('logout').addEventListener('click', () => showLogin('logged out', 'login'));
    window.addEventListener('resize', () => drawChart());
    if (typeof L === 'undefined') {
      setStatus('unreachable', 'Leaflet did not load');
      return;
    }
    loadConfig();
  }

  async function loadConfig() {
    try {
      const response = await fetch('/dashboard/config.json', {cache: 'no-store'});
      if (!response.ok) throw new HttpError(response.status, '');
      state.config = await response.json();
    } catch (err) {
      setStatus('unreachable', `cannot load the dashboard's configuration (${err.message}): retrying`);
      setTimeout(loadConfig, 2000);
      return;
    }
    initMap();
    readCredentials();
    tick();
  }

  start();
}());

/* passt-mav live view: draws the snapshots the server pushes (server-sent events) on a Leaflet map
   with no tile layer (everything comes from the run directory, through 127.0.0.1). */
(function () {
  'use strict';
  var COLORS = ['#e4572e', '#0c8f8c', '#b8860b', '#5a8f29', '#8e44ad', '#2e86de', '#d35400', '#16a085', '#c0392b'];
  // the run's token comes once in the address (?token= or #token=); the page keeps it in sessionStorage, which
  // is per origin (scheme, host and port: never a cookie, which every port of 127.0.0.1 receives), and sends it
  // in the X-Passt-Token header on commands and in the query of its reads (passt_mav/view/gate.py). It leaves
  // the address bar (history, screenshots, shoulders).
  var TOKEN_KEY = 'passt_view_token', token = null;
  (function () {
    var q = new URLSearchParams(location.search), f = new URLSearchParams(location.hash.replace(/^#/, ''));
    var t = f.get('token') || q.get('token');
    try {
      if (t) sessionStorage.setItem(TOKEN_KEY, t);
      token = sessionStorage.getItem(TOKEN_KEY);
    } catch (e) { token = t; }
    if (q.has('token') || f.has('token')) history.replaceState(null, '', location.pathname);
  })();
  function withToken(url) {
    return token ? url + (url.indexOf('?') < 0 ? '?' : '&') + 'token=' + encodeURIComponent(token) : url;
  }
  function $(id) { return document.getElementById(id); }
  function esc(s) { return String(s == null ? '' : s).replace(/[&<>"]/g, function (c) {
    return {'&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;'}[c]; }); }
  function fmt(x, d) { return x == null || isNaN(x) ? '-' : Number(x).toFixed(d == null ? 1 : d); }
  function hms(utc) { try { return new Date(utc).toISOString().substr(11, 8); } catch (e) { return ''; } }
  function dur(s) {
    if (s == null) return '-';
    s = Math.round(s); var h = Math.floor(s / 3600), m = Math.floor(s % 3600 / 60), r = s % 60;
    return (h ? h + ' h ' : '') + (h || m ? m + ' min ' : '') + (h ? '' : r + ' s');
  }

  var map = L.map('map', {preferCanvas: true, zoomSnap: 0.25});
  map.attributionControl.setPrefix('Leaflet 1.9.4 &middot; no tiles: drawn from the run directory');
  map.setView([0, 0], 2);
  var G = {};
  ['speed', 'std', 'land', 'reward', 'fence', 'arrows', 'tracks', 'samples', 'paths', 'boats'].forEach(function (k) {
    G[k] = L.layerGroup();
  });
  ['speed', 'land', 'fence', 'arrows', 'tracks', 'samples', 'paths', 'boats'].forEach(function (k) { G[k].addTo(map); });
  L.control.layers({'estimate: speed': G.speed, 'estimate: posterior std': G.std}, {
    'current arrows': G.arrows, 'reward map of the newest plan': G.reward, 'land': G.land, 'geofence': G.fence,
    'tracks': G.tracks, 'samples (current leg)': G.samples, 'planned paths': G.paths, 'boats': G.boats
  }, {collapsed: false}).addTo(map);
  L.control.scale({imperial: false}).addTo(map);
  var legend = L.control({position: 'bottomleft'});
  legend.onAdd = function () { var d = L.DomUtil.create('div', 'legend'); d.id = 'legend'; return d; };
  legend.addTo(map);

  var overlays = {};   // kind -> url shown
  var markers = {};    // boat -> marker
  var fitted = false, landShown = false, renders = 0;
  window.passtView = {renders: 0, last: null};

  function overlay(kind, url, bounds) {
    if (overlays[kind] === url) return;
    overlays[kind] = url;
    G[kind].clearLayers();
    if (url) L.imageOverlay(withToken(url), bounds, {opacity: kind === 'reward' ? 0.75 : 0.9}).addTo(G[kind]);
  }

  function drawRegion(s) {
    var r = s.region; if (!r) return;
    if (!fitted) { map.fitBounds(r.bounds, {padding: [20, 20]}); fitted = true; }
    if (G.fence.getLayers().length === 0) {
      L.polygon(r.outline, {color: '#345', weight: 1, fill: false}).addTo(G.fence);
      L.polygon(r.fence, {color: '#d11', weight: 2, dashArray: '6 5', fill: false}).bindTooltip('geofence').addTo(G.fence);
    }
    if (r.has_land && !landShown) {
      landShown = true;
      L.imageOverlay(withToken('api/raster/land.png'), r.bounds, {opacity: 1}).addTo(G.land);
    }
    var e = s.estimate;
    if (e && e.leg != null) {
      overlay('speed', 'api/raster/speed.png?leg=' + e.leg + '&v=' + e.kind, r.bounds);
      overlay('std', e.std ? 'api/raster/std.png?leg=' + e.leg : null, r.bounds);
    }
    overlay('reward', e && e.reward_leg != null ? 'api/raster/reward.png?leg=' + e.reward_leg : null, r.bounds);
    drawLegend(e);
  }

  var RAMPS = {speed: '#440154,#3b528b,#21918c,#5ec962,#fde725', std: '#000004,#51127c,#b73779,#fc8961,#fcfdbf',
               reward: '#000004,#57106e,#bc3754,#f98e09,#fcffa4'};
  var base = 'speed';
  map.on('baselayerchange', function (ev) { base = ev.layer === G.std ? 'std' : 'speed'; drawLegend(); });
  map.on('overlayadd overlayremove', function () { drawLegend(); });

  function ramp(kind, lo, hi, what) {
    return '<div>' + what + '</div><div style="display:flex;align-items:center;gap:4px">' + fmt(lo, 3) +
      '<span style="display:inline-block;width:120px;height:9px;background:linear-gradient(to right,' + RAMPS[kind] +
      ')"></span>' + fmt(hi, 3) + '</div>';
  }

  // the unit of every speed and RMSE the server sends (m/s for a mission: passt_mav.units)
  function unitLabel() {
    var s = window.passtView.last;
    return (s && s.units && s.units.label) || 'm/s';
  }

  function drawLegend(e) {
    e = e || (window.passtView.last && window.passtView.last.estimate);
    if (!e || !e.kind) { $('legend').textContent = 'no estimate yet'; return; }
    var when = e.kind === 'estimate' ? 'estimate after leg ' + (e.leg + 1) : 'model forecast of leg ' + (e.leg + 1);
    var html = base === 'std' ? (e.std_range ? ramp('std', e.std_range[0], e.std_range[1],
      'GP posterior std |(std u, std v)|, ' + when + ' (' + unitLabel() + ')') : 'no posterior std yet') :
      ramp('speed', 0, e.vmax, 'speed of the ' + when + ' (' + unitLabel() + ')');
    if (map.hasLayer(G.reward) && e.reward_range) {
      html += ramp('reward', e.reward_range[0], e.reward_range[1], 'reward map that chose leg ' + (e.reward_leg + 1));
    }
    $('legend').innerHTML = html;
  }

  function drawArrows(e) {
    G.arrows.clearLayers();
    if (!e || !e.arrows || !e.arrows.length) return;
    var k = 0.9 * e.cell_m / (e.vmax || 1), segs = [];
    e.arrows.forEach(function (a) {
      var lat = a[0], lon = a[1], c = Math.cos(lat * Math.PI / 180) * 111320;
      var la2 = lat + a[3] * k / 111320, lo2 = lon + a[2] * k / c;
      var ang = Math.atan2(a[3], a[2]), h = 0.3 * k * Math.hypot(a[2], a[3]);
      segs.push([[lat, lon], [la2, lo2]]);
      [2.6, -2.6].forEach(function (d) {
        segs.push([[la2, lo2], [la2 + Math.sin(ang + d) * h / 111320, lo2 + Math.cos(ang + d) * h / c]]);
      });
    });
    L.polyline(segs, {color: '#102030', weight: 1, opacity: 0.75, interactive: false}).addTo(G.arrows);
  }

  function boatIcon(b, hdg) {
    var col = COLORS[b % COLORS.length];
    return L.divIcon({className: 'boat-marker', iconSize: [26, 26], iconAnchor: [13, 13],
      html: '<svg width="26" height="26" viewBox="-13 -13 26 26" style="transform: rotate(' + (hdg || 0) + 'deg)">' +
        '<path d="M0,-12 L7,9 L0,5 L-7,9 Z" fill="' + col + '" stroke="#fff" stroke-width="1.5"/></svg>'});
  }

  function drawBoats(s) {
    G.tracks.clearLayers(); G.samples.clearLayers(); G.paths.clearLayers();
    s.legs.forEach(function (lg) {
      var latest = lg.index === Math.max.apply(null, s.legs.filter(function (x) { return x.boat === lg.boat; })
        .map(function (x) { return x.index; }));
      if (lg.path.length) L.polyline(lg.path, {color: COLORS[lg.boat % COLORS.length], weight: latest ? 3 : 1.5,
        opacity: latest ? 0.95 : 0.35, dashArray: latest ? '8 6' : null}).bindTooltip('boat ' + lg.boat + ', leg ' +
        (lg.index + 1) + ' (' + lg.status + ')').addTo(G.paths);
    });
    s.boats.forEach(function (bt) {
      var b = bt.boat, col = COLORS[b % COLORS.length], st = bt.status || {};
      if (bt.track.length > 1) L.polyline(bt.track, {color: col, weight: 2, opacity: 0.8}).addTo(G.tracks);
      var step = Math.max(1, Math.floor(bt.samples.length / 400));
      for (var i = 0; i < bt.samples.length; i += step) {
        var p = bt.samples[i];
        L.circleMarker([p[0], p[1]], {radius: 2.5, color: col, weight: 1, fillColor: '#fff', fillOpacity: 1})
          .addTo(G.samples);
      }
      if (st.lat == null) return;
      var m = markers[b];
      if (!m) {
        m = markers[b] = L.marker([st.lat, st.lon], {icon: boatIcon(b, st.heading_deg), zIndexOffset: 1000,
          title: 'boat ' + b}).addTo(G.boats);
      } else {
        m.setLatLng([st.lat, st.lon]);
        var svg = m.getElement() && m.getElement().querySelector('svg');
        if (svg) svg.style.transform = 'rotate(' + (st.heading_deg || 0) + 'deg)';
      }
      m.bindTooltip('boat ' + b + ': ' + (st.mode || '?') + ', ' + fmt(st.heading_deg, 0) + '&deg;');
    });
  }

  function row(k, v) { return '<tr><td>' + k + '</td><td>' + v + '</td></tr>'; }

  function drawPanels(s) {
    var html = '';
    s.boats.forEach(function (bt) {
      var st = bt.status || {}, b = bt.boat, age = st.utc ? (Date.now() - Date.parse(st.utc)) / 1000 : null;
      var stale = !s.finished && age != null && age > 5;
      var lost = st.link_lost || stale || ['lost', 'aborted'].indexOf(st.status) >= 0;
      html += '<div class="boat' + (lost ? ' lost' : '') + '" id="boat-' + b + '"><h3><span class="swatch" style="background:' +
        COLORS[b % COLORS.length] + '"></span>boat ' + b + (st.sysid ? ' (sysid ' + st.sysid + ')' : '') +
        ' <span class="pill ' + (lost ? 'bad' : 'ok') + '">' + esc(st.link_lost ? 'LINK LOST' : (stale ? 'no status' :
        (st.status || '-'))) + '</span></h3><table>' +
        row('mode / armed', esc(st.mode || '-') + ' / ' + (st.armed ? 'ARMED' : 'disarmed')) +
        row('link RTT / loss', fmt(st.rtt_ms, 1) + ' ms / ' + fmt(st.loss_pct, 1) + ' %') +
        row('leg', '<span class="leg" data-k="' + (st.leg_k || 0) + '">' + (st.leg_k || '-') + ' of ' +
          (st.legs_n || '-') + '</span> (' + bt.legs_done + ' done)') +
        row('samples this leg', '<span class="nsamples">' + (st.samples_leg || 0) + '</span>') +
        row('time to leg end', dur(st.leg_end_s) + (st.leg_end_wall_s != null ? ' (' + dur(st.leg_end_wall_s) +
          ' wall)' : '')) +
        row('position', '<span class="pos" data-lat="' + (st.lat == null ? '' : st.lat) + '" data-lon="' +
          (st.lon == null ? '' : st.lon) + '">' + fmt(st.lat, 5) + ', ' + fmt(st.lon, 5) + '</span> hdg ' +
          fmt(st.heading_deg, 0) + '&deg;') +
        '</table>' + controls(s, b) + '</div>';
    });
    if (s.boats.length > 1) html = '<div class="boat fleet" id="boat-all"><h3>whole fleet</h3>' + controls(s, 'all') +
      '</div>' + html;
    $('boats').innerHTML = html;
  }

  // -- the operator's console: commands by POST to api/command (the token in X-Passt-Token; view/gate.py) ---
  var ACTIONS = [['pause', 'Pause'], ['resume', 'Resume'], ['skip', 'Skip leg'], ['replan', 'Re-plan now'],
                 ['end:HOLD', 'End (HOLD)'], ['end:RTL', 'End (RTL)']];
  function controls(s, b) {
    var c = s.control || {}, off = !c.token || c.finished;
    var last = (s.commands || []).filter(function (x) { return x.boat === b; }).slice(-1)[0];
    var res = last ? '<div class="cmd-result ' + (last.ok === null ? 'pending' : (last.ok ? 'done' : 'refused')) +
      '" data-action="' + esc(last.action) + '">' + esc(last.action) + (last.end_mode ? ' ' + esc(last.end_mode) : '') +
      ': ' + esc(last.result === null ? 'sent, waiting for the controller' : last.result) + '</div>' : '';
    return approval(s, b, off) + '<div class="controls" data-boat="' + b + '">' + ACTIONS.map(function (a) {
      return '<button type="button" data-act="' + a[0] + '"' + (off ? ' disabled' : '') + '>' + a[1] + '</button>';
    }).join('') + '</div>' + res;
  }

  function approval(s, b, off) {  // approve mode: the leg waiting for the operator (drawn dashed on the map)
    var lg = s.legs.filter(function (x) { return x.boat === b && x.status === 'awaiting_approval'; }).slice(-1)[0];
    if (!lg) return '';
    var a = lg.approval || {};
    return '<div class="approval" data-leg="' + lg.index + '"><b>leg ' + (lg.index + 1) + ' awaits approval</b>: ' +
      lg.waypoints.length + ' waypoints, ' + fmt(a.distance_m, 0) + ' m, ~' + dur(a.expected_s) +
      ' (path dashed on the map, its reward map under "reward map of the newest plan")<div class="controls" ' +
      'data-boat="' + b + '" data-leg="' + lg.index + '"><button type="button" data-act="approve"' +
      (off ? ' disabled' : '') + '>Approve</button><button type="button" data-act="reject"' + (off ? ' disabled' : '') +
      '>Reject (re-plan)</button></div></div>';
  }

  function post(boat, act, leg) {
    var parts = act.split(':'), body = {boat: boat === 'all' ? 'all' : +boat, action: parts[0]};
    if (parts[1]) body.end_mode = parts[1];
    if (leg !== undefined) body.leg = +leg;
    if (parts[0] === 'end' && !window.confirm('End the mission of ' + (boat === 'all' ? 'every boat' : 'boat ' + boat) +
      ' (' + parts[1] + ')?')) return;
    var msg = $('console-msg');
    msg.textContent = 'sending ' + act + ' to boat ' + boat + ' ...'; msg.className = 'small';
    fetch('api/command', {method: 'POST', credentials: 'omit', headers: {'Content-Type': 'application/json',
                          'X-Passt-Token': token || ''}, body: JSON.stringify(body)}).then(function (r) {
      return r.text().then(function (t) {
        msg.textContent = r.status === 202 ? act + ' sent to boat ' + boat + '; the controller answers below' : t;
        msg.className = r.status === 202 ? 'small ok' : 'small bad';
      });
    }).catch(function (e) { msg.textContent = 'not sent: ' + e; msg.className = 'small bad'; });
  }
  $('boats').addEventListener('click', function (ev) {
    var btn = ev.target.closest('button[data-act]'); if (!btn || btn.disabled) return;
    post(btn.parentNode.dataset.boat, btn.dataset.act, btn.parentNode.dataset.leg);
  });

  function drawConsoleNote(s) {
    var c = s.control || {};
    $('console-note').textContent = c.finished ? 'the run has finished: this page is a record' :
      (c.token ? '' : 'read-only: open the address the run printed (with its token) to command the boats');
  }

  // -- alarms: a beep (Web Audio) for each new alert, and a notification while the page is in the background;
  // both need the operator's consent (a click on the checkbox: browsers start audio only after a gesture)
  var audio = null, seenEvents = null;
  window.passtView.beeps = 0;
  $('alarm').addEventListener('change', function () {
    if (!this.checked) return;
    try { audio = audio || new (window.AudioContext || window.webkitAudioContext)(); audio.resume(); } catch (e) {}
    if (window.Notification && Notification.permission === 'default') Notification.requestPermission();
  });
  function beep() {
    window.passtView.beeps += 1;
    if (!audio) return;
    var o = audio.createOscillator(), g = audio.createGain();
    o.frequency.value = 880; g.gain.value = 0.2; o.connect(g); g.connect(audio.destination);
    o.start(); o.stop(audio.currentTime + 0.25);
  }
  function alarm(s) {
    var n = s.n_events, fresh = seenEvents === null ? [] : s.events.slice(Math.max(0, s.events.length - (n - seenEvents)));
    seenEvents = n;
    if (!$('alarm').checked) return;
    fresh.filter(function (e) { return e.level === 'alert'; }).forEach(function (e) {
      beep();
      if (document.hidden && window.Notification && Notification.permission === 'granted') {
        new Notification('passt-mav: boat ' + e.boat, {body: e.text, tag: 'passt-' + e.kind});
      }
    });
  }

  function drawAlerts(s) {
    var notable = s.events.filter(function (e) { return e.level !== 'info'; }).slice(-6).reverse();
    $('alerts').innerHTML = notable.map(function (e) {
      return '<div class="alert level-' + esc(e.level) + ' kind-' + esc(e.kind) + '">' + hms(e.utc) + ' boat ' +
        e.boat + ': ' + esc(e.kind.split('_').join(' ').toUpperCase()) + ' &mdash; ' + esc(e.text) + '</div>';
    }).join('');
    $('events').innerHTML = s.events.slice(-80).reverse().map(function (e) {
      return '<li class="level-' + esc(e.level) + ' kind-' + esc(e.kind) + '">' + hms(e.utc) + ' [' + e.boat + '] ' +
        esc(e.text) + '</li>';
    }).join('');
    var w = s.meta && s.meta.skill_warning;
    $('skill').hidden = !w; $('skill').textContent = w || '';
    var g = s.guard_warning;  // the guard: sampling is not helping (passt_mav.loop.guard)
    $('guard').hidden = !g; $('guard').textContent = g || '';
  }

  function drawRmse(r) {
    var svg = $('rmse'), W = 330, H = 120, P = 28;
    var ys = r.passt.concat(r.model).filter(function (x) { return x != null; });
    if (!ys.length) { svg.innerHTML = '<text x="8" y="60" font-size="12" fill="#667">no leg scored yet ' +
      '(needs the truth: a simulator)</text>'; return; }
    var lo = 0, hi = Math.max.apply(null, ys) * 1.1, n = r.passt.length;
    function X(i) { return P + (n > 1 ? i * (W - P - 8) / (n - 1) : (W - P) / 2); }
    function Y(y) { return H - 16 - (y - lo) / (hi - lo || 1) * (H - 26); }
    function line(a, col, w) {  // the model's line wider, under the estimate's: equal values stay visible
      var pts = a.map(function (y, i) { return y == null ? null : X(i) + ',' + Y(y); }).filter(Boolean).join(' ');
      return '<polyline points="' + pts + '" fill="none" stroke="' + col + '" stroke-width="' + w + '"/>' +
        a.map(function (y, i) { return y == null ? '' : '<circle cx="' + X(i) + '" cy="' + Y(y) + '" r="2.5" fill="' +
          col + '"/>'; }).join('');
    }
    svg.innerHTML = '<line x1="' + P + '" y1="' + (H - 16) + '" x2="' + W + '" y2="' + (H - 16) + '" stroke="#889"/>' +
      '<text x="2" y="14" font-size="10">' + fmt(hi, 3) + '</text><text x="2" y="' + (H - 16) + '" font-size="10">0</text>' +
      '<text x="' + P + '" y="' + (H - 3) + '" font-size="10">after each leg, in field-time order (' + n + ' legs)</text>' +
      line(r.model, '#aaa', 5) + line(r.passt, '#1f6feb', 2);
  }

  function render(s) {
    window.passtView.last = s; window.passtView.renders = ++renders;
    $('title').textContent = 'passt-mav: ' + (s.meta.mission || 'run');
    var rs = $('run-status'); rs.textContent = s.status; rs.className = 'pill ' + (s.status === 'running' ||
      s.status === 'complete' ? 'ok' : 'bad');
    var done = s.legs.filter(function (l) { return l.status === 'complete'; }).length;
    var planned = (s.meta.legs_per_boat || 0) * (s.meta.boats || 1);
    $('legs-done').innerHTML = 'legs done: <b id="legs-done-n">' + done + '</b> of ' + (planned || '-') +
      ' &middot; ' + s.n_samples + ' samples &middot; ' + s.boats.length + ' boat(s)';
    var ft = s.boats.map(function (b) { return (b.status || {}).field_time; }).filter(function (x) { return x != null; });
    $('clock').textContent = ft.length ? 'field time ' + fmt(Math.max.apply(null, ft), 0) : '';
    drawRegion(s); drawArrows(s.estimate); drawBoats(s); drawPanels(s); drawConsoleNote(s); drawAlerts(s); alarm(s);
    $('rmse-unit').textContent = unitLabel();
    drawRmse(s.rmse);
  }

  function connect() {
    var es = new EventSource(withToken('api/stream'));
    es.onopen = function () { var c = $('conn'); c.textContent = 'connected'; c.className = 'pill ok'; };
    es.onmessage = function (ev) {
      try { render(JSON.parse(ev.data)); } catch (err) { console.error(err); }
      // a finished run's page is a record: nothing is connected to a boat any more
      if (window.passtView.last && window.passtView.last.finished) { $('conn').textContent = 'finished'; }
    };
    es.onerror = function () {
      var c = $('conn'); c.className = 'pill bad';
      c.textContent = window.passtView.last && window.passtView.last.finished ? 'server gone (run finished)' :
        'disconnected, retrying';
    };
  }
  connect();
})();

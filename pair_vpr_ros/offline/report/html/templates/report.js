// The keyframe table: rows of the current filter, PAGE at a time, from the rows-NNNN.js chunks
// they live in. State in the address: #filter=false&page=2 (page=all: every matching row).
(function () {
  "use strict";
  var P = window.PAIRVPR, C = window.PAIRVPR_CONFIG, PAGE = 50;
  var table = document.getElementById("keyframes"), body = table.tBodies[0];
  var FILTERS = [
    ["all", "all keyframes"], ["accepted", "accepted"], ["false", "false loops"],
    ["missed", "missed revisits"], ["verification", "rejected by verification"],
    ["pose", "pose refused"]
  ];
  var loading = {};

  function esc(s) {
    return String(s).replace(/[&<>"']/g, function (c) {
      return { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c];
    });
  }
  function num(v, d) { return v === null || v === undefined ? "n/a" : Number(v).toFixed(d); }
  function pad(n) { return ("000" + n).slice(-4); }
  function imgOf(row) { return "img/" + pad(Math.floor(row / 1000)) + "/" + row + ".jpg"; }

  function state() {
    var out = { filter: "all", page: "1" };
    location.hash.slice(1).split("&").forEach(function (kv) {
      var p = kv.split("=");
      if (p.length === 2) { out[p[0]] = decodeURIComponent(p[1]); }
    });
    return out;
  }
  function matching(filter) {
    var flags = P.data.flags, bit = P.data.names[filter], out = [];
    for (var i = 0; i < flags.length; i++) {
      if (filter === "all" || (bit && (flags[i] & bit))) { out.push(i); }
    }
    return out;
  }
  function chunk(n) {
    if (P.chunks[n]) { return Promise.resolve(); }
    if (!loading[n]) {
      loading[n] = new Promise(function (resolve, reject) {
        (P.waiting[n] = P.waiting[n] || []).push(resolve);
        var s = document.createElement("script");
        s.src = "rows/rows-" + pad(n) + ".js";
        s.onerror = function () { reject(new Error("cannot load " + s.src)); };
        document.head.appendChild(s);
      });
    }
    return loading[n];
  }

  function picture(row, cls, alt) {
    if (row === null || row < 0) {
      return '<div class="noimg">no image<br>(prior map, other robot)</div>';
    }
    return '<img class="' + cls + '" src="' + imgOf(row) + '" alt="' + esc(alt) + '">';
  }
  function candidates(r, labels) {
    var chosen = {};
    r.d.forEach(function (d) { chosen[d.m] = true; });
    return '<div class="cands">' + r.c.map(function (c, i) {
      var id = c[0], row = c[1], sim = c[2], pair = c[3], before = c[4], after = c[5];
      var label = labels.charAt(i), score = pair === null ? null : pair + C.weight * sim;
      var mark = label === "t" ? "true place" : label === "f" ? "other place" : "";
      return '<figure class="cand ' + (chosen[before] ? "chosen " : "") + label + '">' +
        picture(row, "c", "keyframe " + id) + "<figcaption>#" + id + (c[6] >= 0 ? " (prior map " + c[6] + ")" : "") +
        "<br>sim " + num(sim, 3) + "<br>pair " + (pair === null ? "not scored" : num(pair, 2)) +
        (pair !== null && C.weight ? "<br>score " + num(score, 2) : "") +
        "<br>rank " + before + "&rarr;" + (after === null ? "&ndash;" : after) +
        (mark ? "<br><b>" + mark + "</b>" : "") + "</figcaption></figure>";
    }).join("") + "</div>";
  }
  function decisions(r) {
    if (!r.d.length) { return '<span class="badge none">no decision</span> ' + esc(r.why || ""); }
    return r.d.map(function (d) {
      var badge = d.a ? '<span class="badge acc">accepted</span>' : '<span class="badge rej">rejected</span>';
      var img = d.img ? '<a href="' + d.img + '"><img class="loop" src="' + d.img + '" alt="loop ' + r.k + " to " + d.id + '"></a>' : "";
      return "<div>" + badge + " &rarr; #" + d.id + ": " + esc(d.why) + img + "</div>";
    }).join("");
  }
  function pose(r) {
    return r.d.filter(function (d) { return d.a; }).map(function (d) {
      if (!d.pose) { return "refused: " + esc(d.pwhy || "no pose"); }
      var sig = d.sig ? "<br>&sigma; " + num(d.sig[0], 3) + " m, " + num(d.sig[1], 2) + "&deg;" : "";
      return esc(d.pose) + (d.t !== null ? ", |t| " + num(d.t, 2) + " m" : "") + sig;
    }).join("<br>");
  }
  function truth(flags) {
    var N = P.data.names;
    if (flags & N.false) { return '<span class="gt-false">false loop</span>'; }
    if (flags & N.true) { return '<span class="gt-true">true loop</span>'; }
    if (flags & N.missed) { return '<span class="gt-missed">missed revisit</span> (a true match existed)'; }
    if (C.truth && (flags & N.accepted)) { return "unlabelled loop (another map, or no pose)"; }
    if (flags & N.revisit) { return "revisit"; }
    return C.truth ? "no true match" : "no ground truth";
  }
  function rowHtml(r) {
    var flags = P.data.flags[r.n], labels = P.data.labels[r.n];
    var kf = r.k >= 0 ? "#" + r.k : "not stored" + (r.r !== null ? " (keyframe #" + r.r + " represents it)" : "");
    return '<tr data-keyframe="' + (r.k >= 0 ? r.k : "q" + r.n) + '" data-row="' + r.n + '" data-flags="' + flags + '">' +
      "<td>" + kf + "<br>" + num(r.s, 3) + " s<br>row " + r.n + "</td>" +
      "<td>" + picture(r.i === false ? -1 : r.n, "q", "query " + r.n) + "</td>" +
      "<td>" + candidates(r, labels) + "</td><td>" + decisions(r) + "</td>" +
      "<td>" + r.d.map(function (d) { return d.inl >= 0 ? d.inl : "&ndash;"; }).join("<br>") + "</td>" +
      "<td>" + pose(r) + "</td><td>" + truth(flags) + "</td></tr>";
  }

  function nav(st, rows) {
    var counts = {};
    FILTERS.forEach(function (f) { counts[f[0]] = matching(f[0]).length; });
    document.getElementById("filters").innerHTML = FILTERS.map(function (f) {
      return '<button data-filter="' + f[0] + '" class="' + (st.filter === f[0] ? "on" : "") + '">' +
        f[1] + " (" + counts[f[0]] + ")</button>";
    }).join("");
    var pages = Math.max(1, Math.ceil(rows.length / PAGE)), html = [];
    for (var p = 1; p <= pages && pages > 1; p++) {
      html.push('<button data-page="' + p + '" class="' + (String(p) === st.page ? "on" : "") + '">' + p + "</button>");
    }
    if (pages > 1) { html.push('<button data-page="all" class="' + (st.page === "all" ? "on" : "") + '">all</button>'); }
    document.getElementById("pager").innerHTML = html.join("");
  }
  function settle(started) {
    var imgs = Array.prototype.slice.call(body.querySelectorAll("img"));
    return Promise.all(imgs.map(function (img) {
      if (img.complete) { return Promise.resolve(); }
      return new Promise(function (r) { img.onload = img.onerror = r; });
    })).then(function () {
      var broken = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
      document.body.dataset.images = imgs.length;
      document.body.dataset.broken = broken.length;
      document.body.dataset.readyMs = Math.round(performance.now() - started);
      document.body.dataset.state = P.errors.length ? "error" : "ready";
    });
  }
  function render() {
    var started = performance.now(), st = state();
    document.body.dataset.state = "loading";
    if (!P.data) {
      body.innerHTML = '<tr><td colspan="7">index.js is missing: the report was not finished.</td></tr>';
      document.body.dataset.state = "error";
      return;
    }
    var rows = matching(st.filter);
    var page = st.page === "all" ? rows : rows.slice((Number(st.page) - 1) * PAGE, Number(st.page) * PAGE);
    nav(st, rows);
    table.dataset.matching = rows.length;
    var need = {};
    page.forEach(function (n) { need[Math.floor(n / P.data.chunk)] = true; });
    Promise.all(Object.keys(need).map(function (n) { return chunk(Number(n)); })).then(function () {
      body.innerHTML = page.map(function (n) {
        return rowHtml(P.chunks[Math.floor(n / P.data.chunk)][n % P.data.chunk]);
      }).join("");
      table.dataset.shown = page.length;
      return settle(started);
    }).catch(function (err) {
      P.errors.push(String(err));
      document.body.dataset.state = "error";
    });
  }
  document.addEventListener("click", function (e) {
    var t = e.target, st = state();
    if (t.dataset && t.dataset.filter) { location.hash = "filter=" + t.dataset.filter + "&page=1"; }
    if (t.dataset && t.dataset.page) { location.hash = "filter=" + st.filter + "&page=" + t.dataset.page; }
  });
  window.addEventListener("hashchange", render);
  render();
})();

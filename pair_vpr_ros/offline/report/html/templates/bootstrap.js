// The data files call these: index.js -> PAIRVPR.index({...}); rows/rows-NNNN.js ->
// PAIRVPR.rows(NNNN, [...]). Loaded as <script> elements: browsers refuse fetch() of file:// URLs.
window.PAIRVPR = {
  data: null,
  chunks: {},
  waiting: {},
  errors: [],
  index: function (data) { this.data = data; },
  rows: function (number, rows) {
    this.chunks[number] = rows;
    var done = this.waiting[number];
    delete this.waiting[number];
    (done || []).forEach(function (f) { f(); });
  }
};
window.addEventListener("error", function (e) {
  window.PAIRVPR.errors.push(String(e.message || (e.target && e.target.src) || e));
}, true);

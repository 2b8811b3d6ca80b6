// pixmuscle report: interactive 3-D view of the model (plotly.js, no network).
// Data: window.PIXMUSCLE_VIEW3D from view3d_data.js (written by pixmuscle/report/view3d.py).
(function () {
  "use strict";
  var root = document.getElementById("view3d");
  if (!root) return;
  var D = window.PIXMUSCLE_VIEW3D;
  var missing = root.querySelector(".view3d-missing");
  if (!D || !window.Plotly) {
    missing.hidden = false;
    return;
  }
  missing.hidden = true;
  var fieldSel = document.getElementById("view3d-field");
  var stepIn = document.getElementById("view3d-step");
  var stepLab = document.getElementById("view3d-step-label");
  var plot = document.getElementById("view3d-plot");
  root.querySelector(".view3d-controls").hidden = false;

  var n = D.tissue.length;
  var FIELDS = {
    umag: {label: "displacement magnitude |u| [cm]", scale: "Viridis"},
    s1: {label: "largest principal Cauchy stress [N/cm²]", scale: "Plasma"},
    tissue: {label: "tissue"},
    muscle: {label: "muscle"},
    fibre: {label: "fibre angle to the long (z) axis [°]", scale: "Cividis"}
  };
  var MUSCLE_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2",
                        "#7f7f7f", "#bcbd22", "#17becf", "#393b79", "#637939", "#8c6d31", "#843c39"];
  var size = n < 3000 ? 5 : n < 20000 ? 3 : 2;

  stepIn.min = 0;
  stepIn.max = D.steps.length - 1;
  stepIn.value = D.steps.length - 1;
  if (!D.s1[0]) fieldSel.querySelector('option[value="s1"]').disabled = true;

  // colour range of a field over every step, so the slider compares steps on one scale
  function range(key) {
    var lo = Infinity, hi = -Infinity;
    D[key].forEach(function (a) {
      if (!a) return;
      for (var i = 0; i < a.length; i++) {
        var v = a[i];
        if (v === null || isNaN(v)) continue;
        if (v < lo) lo = v;
        if (v > hi) hi = v;
      }
    });
    if (!isFinite(lo)) { lo = 0; hi = 1; }
    if (hi <= lo) hi = lo + 1e-9;
    return [lo, hi];
  }
  var RANGES = {umag: range("umag"), s1: range("s1")};

  function coords(s, idx) {
    var X = D.X, u = D.u[s], x = [], y = [], z = [];
    idx.forEach(function (i) {
      x.push(X[3 * i] + u[3 * i]);
      y.push(X[3 * i + 1] + u[3 * i + 1]);
      z.push(X[3 * i + 2] + u[3 * i + 2]);
    });
    return {x: x, y: y, z: z};
  }

  function allIdx(pred) {
    var out = [];
    for (var i = 0; i < n; i++) if (pred(i)) out.push(i);
    return out;
  }

  function cloud(s, idx, name, marker, extra) {
    var c = coords(s, idx);
    var t = {type: "scatter3d", mode: "markers", name: name, x: c.x, y: c.y, z: c.z, marker: marker,
             hoverinfo: "name+text", text: extra || undefined};
    return t;
  }

  function colourbar(title) {
    return {title: {text: title, side: "right", font: {size: 14}}, tickfont: {size: 13}, len: 0.85,
            thickness: 18, outlinewidth: 0};
  }

  function continuous(s, values, key, title, scale) {
    var idx = allIdx(function (i) { return !isNaN(values[i]); });
    var rest = allIdx(function (i) { return isNaN(values[i]); });
    var c = idx.map(function (i) { return values[i]; });
    var r = key === "fibre" ? [0, 90] : RANGES[key];
    var traces = [cloud(s, idx, title, {size: size, color: c, colorscale: scale, cmin: r[0], cmax: r[1],
                                        showscale: true, colorbar: colourbar(title)},
                        c.map(function (v) { return v.toPrecision(4); }))];
    traces[0].showlegend = false;
    if (rest.length) {
      var t = cloud(s, rest, key === "fibre" ? "no fibre (not muscle)" : "no value",
                    {size: size, color: "#cccccc", opacity: 0.35});
      traces.push(t);
    }
    return traces;
  }

  function categorical(s, classOf, classes) {
    var traces = [];
    classes.forEach(function (cl, k) {
      var idx = allIdx(function (i) { return classOf[i] === k; });
      if (idx.length) traces.push(cloud(s, idx, cl.name + " (" + idx.length + ")", {size: size, color: cl.color}));
    });
    return traces;
  }

  function traces(field, s) {
    if (field === "umag") return continuous(s, D.umag[s], "umag", FIELDS.umag.label, FIELDS.umag.scale);
    if (field === "s1") return continuous(s, D.s1[s], "s1", FIELDS.s1.label, FIELDS.s1.scale);
    if (field === "fibre") return continuous(s, D.fibre_angle, "fibre", FIELDS.fibre.label, FIELDS.fibre.scale);
    if (field === "tissue") return categorical(s, D.tissue, D.tissue_classes);
    var classes = [{name: "not muscle", color: "#d0d0d0"}].concat(D.muscle_names.map(function (m, k) {
      return {name: m, color: MUSCLE_COLOURS[k % MUSCLE_COLOURS.length]};
    }));
    return categorical(s, D.muscle, classes);
  }

  var layout = {
    uirevision: "keep", // rotation and zoom stay when the field or step changes
    margin: {l: 0, r: 0, t: 30, b: 0},
    scene: {aspectmode: "data", xaxis: {title: {text: "x [cm]"}}, yaxis: {title: {text: "y [cm]"}},
            zaxis: {title: {text: "z [cm]"}}, camera: {eye: {x: 1.4, y: 1.4, z: 0.9}}},
    legend: {font: {size: 13}, itemsizing: "constant", x: 0, y: 1},
    font: {size: 13},
    title: {text: "", font: {size: 14}}
  };

  function draw() {
    var field = fieldSel.value, s = Number(stepIn.value);
    stepLab.textContent = "step " + D.steps[s] + " (α = " + D.alpha[s].toFixed(3) + ")";
    layout.title.text = FIELDS[field].label + " on the deformed body, step " + D.steps[s];
    plot.dataset.drawn = "0";
    return Plotly.react(plot, traces(field, s), layout, {responsive: true, displaylogo: false})
      .then(function () {
        plot.dataset.field = field;
        plot.dataset.step = String(D.steps[s]);
        plot.dataset.drawn = "1";
      });
  }

  fieldSel.addEventListener("change", draw);
  stepIn.addEventListener("input", draw);
  draw();
})();

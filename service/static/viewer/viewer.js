// The TDCR shape viewer: sliders -> debounced POST /predict and POST /exact -> three.js drawing.
// Everything in SI units from the service; shown in friendlier units.  For tests, <body> carries
// data-updates (answers drawn), data-design (the design drawn, JSON), data-error (relative l2) and
// data-error-bound (the operator's calibrated bound, or "none") and data-tendon-points (the points
// drawn of each exact tendon path: a tendon that ends before the tip is drawn to its end).
"use strict";
(function () {
  const DEBOUNCE_MS = 150;
  const SLIDER_STEPS = 500;
  const COLORS = { exact: 0x1f5fbf, predicted: 0xe0692b, background: 0xffffff };
  const ROD = ["E", "r", "L"];
  const TENDON = ["offset", "pitch", "tension"];
  // parameter -> [factor from SI, unit shown, decimals]
  const DISPLAY = { E: [1e-9, "GPa", 2], r: [1e3, "mm", 3], L: [1e3, "mm", 1], offset: [1e3, "mm", 2],
                    pitch: [1, "rad/m", 2], tension: [1, "N", 2], density: [1, "kg/m³", 0],
                    tip_force: [1e3, "mN", 2], end: [1, "× L", 2] };
  const END_RANGE = [0.05, 1];  // where a tendon ends, as a fraction of L (1: the tip)
  const GRAVITY = 9.81;  // m/s^2
  const AXES = ["x", "y", "z"];
  const el = (id) => document.getElementById(id);
  const body = document.body;

  let space = null;          // GET /design-space
  const sliders = {};        // key ("E", "tension_2", ...) -> {input, output, param}
  let sequence = 0;          // the latest request wins
  let timer = null;
  let view = null;           // three.js state
  let drawnOnce = false;
  let manifest = null;       // GET /models
  body.dataset.updates = "0";

  // -- the design --------------------------------------------------------------------------

  function tableRange(param) {
    if (param === "end") return END_RANGE;
    if (param in space.loads) return loadRange(param);
    const p = space.parameters[param];
    const [lo, hi] = p.table_i;
    if (!el("beyond").checked) return [lo, hi];
    const [alo, ahi] = p.admissible;  // Table I widened by its own width each side, within the admissible bounds
    const width = hi - lo;
    const low = Math.max(alo, lo - width);
    return [p.exclusive_min && low === alo ? alo + width / SLIDER_STEPS : low, Math.min(ahi, hi + width)];
  }

  function loadRange(param) {  // the loaded operators' training loads; a tip force per component in [-|F|, |F|]
    const load = space.loads[param];
    const [lo, hi] = param === "density" ? load.trained : [-load.trained[1], load.trained[1]];
    if (!el("beyond").checked) return [lo, hi];
    const [alo, ahi] = load.admissible;
    const width = hi - lo;
    return [Math.max(param === "density" ? alo + width / SLIDER_STEPS : alo, lo - width), Math.min(ahi, hi + width)];
  }

  function setRange(slider, lo, hi) {
    slider.input.min = String(lo);
    slider.input.max = String(hi);
    slider.input.step = String((hi - lo) / SLIDER_STEPS);
  }

  function showValue(slider) {
    const [factor, unit, decimals] = DISPLAY[slider.param];
    slider.output.value = `${(Number(slider.input.value) * factor).toFixed(decimals)} ${unit}`;
  }

  function addSlider(parent, key, param, label, value) {
    const id = `p-${key}`;
    const wrap = document.createElement("div");
    wrap.className = "param";
    const lab = document.createElement("label");
    lab.htmlFor = id;
    lab.textContent = label;
    const input = document.createElement("input");
    input.type = "range";
    input.id = id;
    const output = document.createElement("output");
    output.htmlFor = id;
    wrap.append(lab, input, output);
    parent.append(wrap);
    const slider = { input, output, param };
    const [lo, hi] = tableRange(param);
    setRange(slider, lo, hi);
    input.value = String(value);
    input.setAttribute("aria-describedby", `${id}-unit`);
    output.id = `${id}-unit`;
    showValue(slider);
    input.addEventListener("input", () => { showValue(slider); schedule(); });
    sliders[key] = slider;
  }

  function buildControls() {
    const n = space.n_tendons;
    const mid = (param) => space.parameters[param].table_i.reduce((a, b) => a + b) / 2;
    const rod = el("rod");
    ROD.forEach((p) => addSlider(rod, p, p, p === "E" ? "E" : p, mid(p)));
    const tendons = el("tendons");
    for (let i = 0; i < n; i++) {
      const fs = document.createElement("fieldset");
      const legend = document.createElement("legend");
      legend.textContent = `Tendon ${i + 1}`;
      fs.append(legend);
      const start = { offset: mid("offset"), pitch: 0, tension: i === 0 ? 2 : 0 };
      TENDON.forEach((p) => addSlider(fs, `${p}_${i}`, p, p, start[p]));
      addSlider(fs, `end_${i}`, "end", "ends at", 1);  // below 1: segments (the exact solver alone)
      tendons.append(fs);
    }
    const loads = el("loads");
    addSlider(loads, "density", "density", "density", 7800);
    AXES.forEach((axis) => addSlider(loads, `tip_force_${axis}`, "tip_force", `tip F${axis}`, 0));
  }

  function currentLoads() {  // the design's load fields (none when zero)
    const fields = {};
    const gravity = el("gravity").value;
    if (gravity !== "none") {
      fields.gravity = gravity.split(",").map((v) => GRAVITY * Number(v));
      fields.density = Number(sliders.density.input.value);
    }
    const force = AXES.map((axis) => Number(sliders[`tip_force_${axis}`].input.value));
    if (force.some((v) => v !== 0)) fields.tip_force = force;
    return fields;
  }

  function takesLoads(name) { return "loads" in ((manifest.models[name] || {}).inputs || {}); }

  function operatorFor(loaded) {  // a loaded operator for a design with loads
    const select = el("model");
    const loadedOperator = manifest.default_loaded_operator || manifest.default_loaded_model;
    if (loaded && !takesLoads(select.value) && loadedOperator) {
      select.value = loadedOperator;
      el("message").textContent = `The design has loads: switched to the loaded operator ${select.value}.`;
    }
    return select.value;
  }

  function currentDesign() {
    const value = (key) => Number(sliders[key].input.value);
    const design = { E: value("E"), r: value("r"), L: value("L"), tendons: [] };
    for (let i = 0; i < space.n_tendons; i++) {
      const tendon = { offset: value(`offset_${i}`), pitch: value(`pitch_${i}`), tension: value(`tension_${i}`) };
      if (value(`end_${i}`) < 1) tendon.end = value(`end_${i}`) * design.L;
      design.tendons.push(tendon);
    }
    return Object.assign(design, currentLoads());
  }

  function applyDesign(design) {
    const values = { E: design.E, r: design.r, L: design.L };
    if (!Array.isArray(design.tendons) || design.tendons.length !== space.n_tendons) {
      throw new Error(`a design needs "tendons": a list of ${space.n_tendons}`);
    }
    design.tendons.forEach((t, i) => {
      TENDON.forEach((p) => { values[`${p}_${i}`] = t[p]; });
      values[`end_${i}`] = t.end == null ? 1 : t.end / design.L;
    });
    for (const [key, v] of Object.entries(values)) {
      if (typeof v !== "number" || !Number.isFinite(v)) throw new Error(`${key} must be a number`);
    }
    const outside = Object.entries(values).some(([key, v]) => {
      const [lo, hi] = space.parameters[sliders[key].param].table_i;
      return v < lo || v > hi;
    });
    if (outside && !el("beyond").checked) { el("beyond").checked = true; updateRanges(); }
    for (const [key, v] of Object.entries(values)) {
      const slider = sliders[key];
      const [lo, hi] = [Number(slider.input.min), Number(slider.input.max)];
      if (v < lo || v > hi) setRange(slider, Math.min(lo, v), Math.max(hi, v));
      slider.input.value = String(v);
      showValue(slider);
    }
    schedule(0);
  }

  function updateRanges() {
    for (const slider of Object.values(sliders)) {
      const [lo, hi] = tableRange(slider.param);
      const v = Math.min(Math.max(Number(slider.input.value), lo), hi);
      setRange(slider, lo, hi);
      slider.input.value = String(v);
      showValue(slider);
    }
  }

  // -- the answers -------------------------------------------------------------------------

  async function post(path, payload) {
    const started = performance.now();
    const response = await fetch(path, { method: "POST", headers: { "content-type": "application/json" },
                                         body: JSON.stringify(payload) });
    const answer = await response.json();
    const ms = performance.now() - started;
    if (!response.ok) throw new Error(`${path}: ${answer.message || answer.error || response.status}`);
    return { result: answer.results[0], model: answer.model, ms };
  }

  function schedule(delay = DEBOUNCE_MS) {
    clearTimeout(timer);
    timer = setTimeout(update, delay);
  }

  async function update() {
    const mine = ++sequence;
    const design = currentDesign();
    const points = space.default_points;
    const model = operatorFor(Object.keys(design).some((k) => k in space.loads));
    const segmented = design.tendons.some((t) => "end" in t);  // the operators take tendons to the tip
    try {
      const [predicted, exact] = await Promise.all([
        segmented ? Promise.resolve(null) : post("/predict", { model, designs: [design], points }),
        post("/exact", { designs: [design], points }),
      ]);
      if (mine !== sequence) return;  // a newer design is on its way
      if (segmented) {
        el("message").textContent = "A tendon ends before the tip: the exact solver alone (the operators take " +
          "tendons that end at the tip).";
      } else if (!el("message").textContent.startsWith("The design has loads")) el("message").textContent = "";
      draw(design, predicted && predicted.result, exact.result);
      showNumbers(predicted, exact);
      body.dataset.design = JSON.stringify(design);
      body.dataset.updates = String(Number(body.dataset.updates) + 1);
    } catch (err) {
      if (mine === sequence) el("message").textContent = err.message;
    }
  }

  function relativeL2(pred, truth) {  // tdcr.metrics.relative_l2 of one design: ||pred - truth|| / ||truth||
    let num = 0, den = 0;
    const walk = (p, t) => {
      if (Array.isArray(t)) { t.forEach((ti, i) => walk(p[i], ti)); return; }
      num += (p - t) ** 2;
      den += t ** 2;
    };
    walk(pred, truth);
    return Math.sqrt(num / den);
  }

  function showNumbers(predicted, exact) {
    const x = exact.result;
    el("exact-time").textContent = `${exact.ms.toFixed(1)} ms`;
    el("converged").textContent = x.converged ? "yes" : `no (residual ${x.residual})`;
    if (predicted === null) {  // no operator answer to compare
      body.dataset.error = body.dataset.errorBound = body.dataset.tipError = "none";
      ["error", "error-bound", "tip-error", "predict-time", "warnings"].forEach((id) => { el(id).textContent = "–"; });
      return;
    }
    const p = predicted.result;
    const error = relativeL2(p.tendons, x.tendons);
    body.dataset.error = String(error);
    el("error").textContent = `${error.toExponential(3)} (${(100 * error).toFixed(3)} %)`;
    // the operator's own bound on that error (null: outside the calibrated region, or uncalibrated)
    const bound = p.error_bound;
    body.dataset.errorBound = bound == null ? "none" : String(bound);
    el("error-bound").textContent = bound == null ? "none: outside the calibrated region"
      : `${bound.toExponential(3)} ${error <= bound ? "(the error is within it)" : "(exceeded: 1 answer in 100 may)"}`;
    const n = x.backbone.length - 1;
    const tip = Math.hypot(...p.backbone[n].map((v, i) => v - x.backbone[n][i])) * 1e3;
    body.dataset.tipError = String(tip);
    el("tip-error").textContent = `${tip.toFixed(3)} mm`;
    const badge = el("badge");
    badge.textContent = p.in_distribution ? "in distribution" : "out of distribution";
    badge.className = `badge ${p.in_distribution ? "in" : "out"}`;
    el("warnings").textContent = (p.warnings || []).join("; ");
    el("predict-time").textContent = `${predicted.model}: ${predicted.ms.toFixed(1)} ms`;
  }

  // -- the 3-D view ------------------------------------------------------------------------

  function setupView() {
    const canvas = el("canvas");
    const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    const scene = new THREE.Scene();
    scene.background = new THREE.Color(COLORS.background);
    scene.add(new THREE.AmbientLight(0xffffff, 0.55));
    const sun = new THREE.DirectionalLight(0xffffff, 0.75);
    sun.position.set(1, 2, 1.5);
    scene.add(sun);
    const camera = new THREE.PerspectiveCamera(40, 1, 1e-4, 100);
    const controls = new THREE.OrbitControls(camera, canvas);
    const robot = new THREE.Group();
    robot.rotation.x = -Math.PI / 2;  // the robot's base z axis points up on screen
    scene.add(robot);
    const grid = new THREE.GridHelper(1, 20, 0xcccccc, 0xe6e6e6);
    scene.add(grid);
    view = { renderer, scene, camera, controls, robot, grid, canvas };
    const render = () => renderer.render(scene, camera);
    view.render = render;
    controls.addEventListener("change", render);
    const resize = () => {
      const { clientWidth: w, clientHeight: h } = canvas;
      if (!w || !h) return;
      renderer.setSize(w, h, false);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
      render();
    };
    new ResizeObserver(resize).observe(canvas);
    resize();
  }

  function vectors(points) { return points.map(([x, y, z]) => new THREE.Vector3(x, y, z)); }

  function shape(design, result, kind) {
    const group = new THREE.Group();
    const predicted = kind === "predicted";
    const color = COLORS[kind];
    const curve = new THREE.CatmullRomCurve3(vectors(result.backbone));
    const radius = Math.max(design.r, design.L / 120);  // visible at any zoom
    const tube = new THREE.Mesh(
      new THREE.TubeGeometry(curve, 4 * result.backbone.length, radius, 12, false),
      new THREE.MeshStandardMaterial({ color, roughness: 0.5, transparent: predicted, opacity: predicted ? 0.45 : 1 }));
    group.add(tube);
    const tendonCount = result.tendons[0].length;
    const drawnPoints = [];
    for (let i = 0; i < tendonCount; i++) {
      // to its end: the answer holds a tendon's termination point at every s beyond it
      const end = (design.tendons[i].end ?? design.L) / design.L;
      const inside = result.s.filter((s) => s <= end + 1e-12).length;
      const path = result.tendons.slice(0, Math.min(result.s.length, inside + 1)).map((node) => node[i]);
      drawnPoints.push(path.length);
      const geometry = new THREE.BufferGeometry().setFromPoints(vectors(path));
      const material = predicted
        ? new THREE.LineDashedMaterial({ color, dashSize: design.L / 80, gapSize: design.L / 160 })
        : new THREE.LineBasicMaterial({ color: 0x222222 });
      const line = new THREE.Line(geometry, material);
      if (predicted) line.computeLineDistances();
      group.add(line);
    }
    if (!predicted) body.dataset.tendonPoints = JSON.stringify(drawnPoints);
    if (!predicted) {  // spacer disks, oriented by the frames R(s)
      const maxOffset = Math.max(...design.tendons.map((t) => t.offset));
      const disk = new THREE.CylinderGeometry(maxOffset * 1.25, maxOffset * 1.25, design.L / 300, 24);
      disk.rotateX(Math.PI / 2);  // its axis along the local z (the backbone tangent)
      const material = new THREE.MeshStandardMaterial({ color: 0x9aa3ad, roughness: 0.6 });
      const every = Math.max(1, Math.round(result.backbone.length / 10));
      for (let k = 0; k < result.backbone.length; k += every) {
        const R = result.rotation[k];
        const frame = new THREE.Matrix4().set(R[0][0], R[0][1], R[0][2], result.backbone[k][0],
                                              R[1][0], R[1][1], R[1][2], result.backbone[k][1],
                                              R[2][0], R[2][1], R[2][2], result.backbone[k][2],
                                              0, 0, 0, 1);
        const mesh = new THREE.Mesh(disk, material);
        mesh.applyMatrix(frame);
        group.add(mesh);
      }
    }
    return group;
  }

  function dispose(object) {
    object.traverse((o) => {
      if (o.geometry) o.geometry.dispose();
      if (o.material) o.material.dispose();
    });
  }

  function draw(design, predicted, exact) {
    const robot = view.robot;
    while (robot.children.length) { const child = robot.children.pop(); dispose(child); }
    robot.add(shape(design, exact, "exact"));
    if (predicted) robot.add(shape(design, predicted, "predicted"));
    if (!drawnOnce) { fit(design); drawnOnce = true; }
    view.render();
  }

  function fit(design) {
    const { camera, controls, robot, grid } = view;
    robot.updateMatrixWorld(true);
    const box = new THREE.Box3().setFromObject(robot);
    const sphere = box.getBoundingSphere(new THREE.Sphere());
    const radius = Math.max(sphere.radius, design.L / 2);
    const distance = radius / Math.sin((camera.fov * Math.PI) / 360) * 1.15;
    controls.target.copy(sphere.center);
    camera.position.copy(sphere.center).add(new THREE.Vector3(1, 0.6, 1).normalize().multiplyScalar(distance));
    camera.near = distance / 1000;
    camera.far = distance * 100;
    camera.updateProjectionMatrix();
    grid.scale.setScalar(design.L * 2);
    controls.update();
  }

  // -- start -------------------------------------------------------------------------------

  async function start() {
    try {
      const [designSpace, models] = await Promise.all([fetch("/design-space"), fetch("/models")]);
      if (!designSpace.ok || !models.ok) throw new Error("the service did not answer /design-space or /models");
      space = await designSpace.json();
      manifest = await models.json();
      const select = el("model");
      for (const name of manifest.loaded) {
        const option = document.createElement("option");
        option.value = option.textContent = name;
        option.selected = name === (manifest.default_operator || manifest.default_model);
        select.append(option);
      }
      buildControls();
      setupView();
      select.addEventListener("change", () => { el("message").textContent = ""; schedule(0); });
      el("gravity").addEventListener("change", () => schedule(0));
      el("beyond").addEventListener("change", () => { updateRanges(); schedule(0); });
      el("reset").addEventListener("click", () => { fit(currentDesign()); view.render(); });
      el("apply").addEventListener("click", () => {
        try {
          const parsed = JSON.parse(el("paste").value);
          applyDesign(Array.isArray(parsed.designs) ? parsed.designs[0] : parsed);
          el("message").textContent = "";
        } catch (err) {
          el("message").textContent = `Not applied: ${err.message}`;
        }
      });
      el("copy").addEventListener("click", () => { el("paste").value = JSON.stringify(currentDesign(), null, 1); });
      schedule(0);
    } catch (err) {
      el("message").textContent = err.message;
    }
  }

  start();
})();

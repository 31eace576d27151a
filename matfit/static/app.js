// matfit serve: the page. Talks to the JSON API of matfit/app/serve/routes.py; no library, nothing from the internet.
"use strict";
const $ = (id) => document.getElementById(id);
const state = { parameters: [], presets: {}, values: [], init: null, lastFit: null, renderJob: null };

function showError(message) {
  $("error").textContent = message;
  $("error").hidden = !message;
}
function setStatus(text) { $("status").textContent = text; }

async function api(path, options) {
  const response = await fetch(path, options);
  const body = await response.json().catch(() => ({ error: `the server answered ${response.status}` }));
  if (!response.ok && body.state !== "error") throw new Error(body.error || `the server answered ${response.status}`);
  return body;
}

// --- fitting -------------------------------------------------------------------------------------
async function fitFile(file, mask) {
  showError("");
  if (file !== state.file) startMask(file);
  state.file = file;
  const form = new FormData();
  form.append("image", file, file.name);
  if (mask) form.append("mask", mask, "mask.png");
  if (state.init) form.append("init", JSON.stringify(state.init));
  setStatus(`uploading ${file.name}`);
  try {
    const { job } = await api("/api/fit", { method: "POST", body: form });
    await follow(job, file.name);
  } catch (error) {
    setStatus("ready");
    showError(error.message);
  }
}

async function follow(job, name) {
  let early = null; // the stage of the running fit's answer on show
  for (;;) {
    const answer = await api(`/api/jobs/${job}`);
    $("bar").style.width = `${Math.round(100 * answer.progress)}%`;
    if (answer.state === "done") return showFit(job, answer.result, name);
    if (answer.state === "error") { setStatus("ready"); return showError(answer.error); }
    if (answer.state === "superseded" || answer.state === "cancelled") return;
    if (answer.result && answer.result.stage !== early) { early = answer.result.stage; showAnswer(answer.result, name); }
    setStatus(`${name}: ${answer.stage}`);
    await new Promise((resolve) => setTimeout(resolve, 60));
  }
}

// The pictures of a fit or of a stage's answer; Mitsuba's and the difference hidden where it has none yet.
function showPictures(result) {
  for (const key of ["target", "start", "neural", "mitsuba", "difference"]) {
    const picture = result.pictures[key];
    $(`pic-${key}`).closest("figure").hidden = !picture;
    if (picture) $(`pic-${key}`).src = picture;
  }
  $("result").hidden = false;
}

// A stage's answer while the fit runs (the neural search's first, not yet checked in Mitsuba): its pictures, figures,
// sliders and neural preview at once; the next stage's, then the fit's own (`showFit`), replace it. No downloads yet.
function showAnswer(result, name) {
  showPictures(result);
  const checked = result.mitsuba_checked ? `Mitsuba ${result.mitsuba_rmse.toFixed(2)}` : "not yet checked in Mitsuba";
  $("figures").textContent =
    `${name}: ${result.stage} answer, neural RMSE ${result.neural_rmse.toFixed(2)}, ${checked} ` +
    `(${result.seconds.toFixed(2)} s; the fit goes on)`;
  $("figures").dataset.stage = result.stage;
  $("downloads").hidden = true;
  setValues(result.values);
  showRanges(result.ranges);
}

function showFit(job, result, name) {
  showPictures(result);
  $("figures").textContent =
    `${name}: neural RMSE ${result.neural_rmse.toFixed(2)}, Mitsuba RMSE ${result.mitsuba_rmse.toFixed(2)} ` +
    `(start ${result.start} ${result.start_rmse.toFixed(2)}; kept ${result.kept}), ${result.seconds.toFixed(2)} s` +
    (result.mask ? ", masked" : "");
  $("figures").dataset.job = job;
  $("figures").dataset.stage = result.stage;
  const links = { "dl-params": "params.json", "dl-xml": "material.xml", "dl-blender": "material.py", "dl-report": "report.png" };
  for (const [id, file] of Object.entries(links)) $(id).href = `/api/jobs/${job}/files/${file}`;
  $("downloads").hidden = false;
  $("bar").style.width = "100%";
  setStatus(`fitted ${name}`);
  state.lastFit = result.values;
  setValues(result.values);
  addOption("last fit", "__last");
  showRanges(result.ranges);
}

// What the picture decides (docs/fitting.md#what-the-picture-decides): each slider's range as a band under it,
// coloured by verdict, and the look-alikes as buttons that set the sliders, as a preset does.
function showRanges(ranges) {
  state.parameters.forEach((p, i) => {
    const band = $(`band-${p.name}`), slider = $(`slider-${p.name}`);
    const range = ranges && ranges.parameters[i];
    band.hidden = !range;
    if (!range) { slider.title = ""; return; }
    const at = (v) => (100 * (v - p.low)) / (p.high - p.low);
    band.style.left = `${at(range.low)}%`;
    band.style.width = `${Math.max(at(range.high) - at(range.low), 0.5)}%`;
    band.dataset.verdict = range.verdict;
    slider.title = `${range.verdict} by the picture: ${range.low} to ${range.high} ${p.unit} look the same (within ${ranges.threshold_rmse} RMSE)`;
  });
  const box = $("look-alikes");
  box.replaceChildren();
  for (const alike of (ranges && ranges.look_alikes) || []) {
    const button = document.createElement("button");
    button.textContent = alike.label;
    button.title = `decodes within ${alike.rmse.toFixed(2)} RMSE of the fit: click to start from it`;
    button.addEventListener("click", () => {
      state.init = alike.values; // a starting point: it joins the candidates of the next fits, as a loaded params.json
      $("init-note").textContent = `look-alike ${alike.label}: joins the candidates of the next fits`;
      setValues(alike.values);
    });
    box.append(button);
  }
  $("look-alikes-row").hidden = !box.childElementCount;
}

// --- the mask: white = fit here, black = ignore; the size of the uploaded picture ----------------------------------
const mask = { canvas: document.createElement("canvas"), picture: new Image(), painting: false };

function startMask(file) {
  mask.picture.onload = () => {
    mask.canvas.width = mask.picture.naturalWidth;
    mask.canvas.height = mask.picture.naturalHeight;
    clearMask();
  };
  mask.picture.src = URL.createObjectURL(file);
}

function clearMask() {
  const context = mask.canvas.getContext("2d");
  context.fillStyle = "#fff";
  context.fillRect(0, 0, mask.canvas.width, mask.canvas.height);
  mask.painted = false;
  drawMask();
}

function drawMask() {
  const view = $("mask-view").getContext("2d");
  view.globalCompositeOperation = "source-over";
  view.globalAlpha = 1;
  view.drawImage(mask.picture, 0, 0, 256, 256);
  view.globalCompositeOperation = "multiply";
  view.globalAlpha = 0.7;
  view.drawImage(mask.canvas, 0, 0, 256, 256);
}

function paint(event) {
  if (!mask.painting || !mask.canvas.width) return;
  const box = $("mask-view").getBoundingClientRect();
  const scale = mask.canvas.width / box.width;
  const context = mask.canvas.getContext("2d");
  context.fillStyle = document.querySelector("input[name=brush]:checked").value === "fit" ? "#fff" : "#000";
  context.beginPath();
  context.arc((event.clientX - box.left) * scale, (event.clientY - box.top) * mask.canvas.height / box.height,
    Number($("brush-size").value) * scale / 2, 0, 2 * Math.PI);
  context.fill();
  mask.painted = true;
  drawMask();
}

function fitWithMask() {
  if (!state.file) return showError("choose a picture first: the mask is painted on it");
  mask.canvas.toBlob((blob) => fitFile(state.file, blob), "image/png");
}

// --- adjusting -----------------------------------------------------------------------------------
function addOption(label, value) {
  if ([...$("start").options].some((o) => o.value === value)) return;
  const option = document.createElement("option");
  option.value = value;
  option.textContent = label;
  $("start").append(option);
}

function buildSliders() {
  const box = $("sliders");
  state.parameters.forEach((p, i) => {
    if (p.name.endsWith("_r")) {
      const picker = document.createElement("label");
      picker.className = "colour";
      const input = document.createElement("input");
      input.type = "color";
      input.id = `colour-${p.name.slice(0, -2)}`;
      input.addEventListener("input", () => {
        const hex = input.value;
        [0, 1, 2].forEach((k) => { state.values[i + k] = parseInt(hex.slice(1 + 2 * k, 3 + 2 * k), 16) / 255; });
        setValues(state.values);
        preview();
      });
      picker.append(`${p.name.slice(0, -2)} `, input);
      box.append(picker);
    }
    const label = document.createElement("label");
    label.textContent = p.name;
    label.title = p.meaning;
    label.htmlFor = `slider-${p.name}`;
    const slider = document.createElement("input");
    Object.assign(slider, { type: "range", id: `slider-${p.name}`, min: p.low, max: p.high, step: (p.high - p.low) / 1000 });
    slider.addEventListener("input", () => { state.values[i] = Number(slider.value); showValue(i); preview(); });
    const track = document.createElement("span");
    track.className = "track";
    const band = document.createElement("span");
    Object.assign(band, { className: "band", id: `band-${p.name}`, hidden: true });
    track.append(slider, band);
    const output = document.createElement("output");
    output.id = `value-${p.name}`;
    const unit = document.createElement("span");
    unit.className = "unit";
    unit.textContent = p.unit;
    box.append(label, track, output, unit);
  });
}

function showValue(i) {
  const p = state.parameters[i];
  $(`value-${p.name}`).textContent = state.values[i].toFixed(3);
  const base = p.name.slice(0, -2);
  if (/_[rgb]$/.test(p.name) && $(`colour-${base}`)) {  // a colour's channel (phase_g is not one)
    const first = state.parameters.findIndex((q) => q.name === `${base}_r`);
    const hex = [0, 1, 2].map((k) => Math.round(255 * Math.min(1, Math.max(0, state.values[first + k]))).toString(16).padStart(2, "0"));
    $(`colour-${base}`).value = `#${hex.join("")}`;
  }
}

function setValues(values) {
  state.values = values.map(Number);
  state.parameters.forEach((p, i) => { $(`slider-${p.name}`).value = state.values[i]; showValue(i); });
  preview();
}

let previewBusy = false, previewAgain = false;
async function preview() {
  if (previewBusy) { previewAgain = true; return; }
  previewBusy = true;
  const started = performance.now();
  try {
    const response = await fetch("/api/preview", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ values: state.values }) });
    if (!response.ok) throw new Error((await response.json()).error);
    const old = $("preview").src;
    $("preview").src = URL.createObjectURL(await response.blob());
    if (old.startsWith("blob:")) URL.revokeObjectURL(old);
    $("preview-ms").textContent = Math.round(performance.now() - started);
    $("preview").dataset.count = String(Number($("preview").dataset.count || 0) + 1);
  } catch (error) {
    showError(error.message);
  } finally {
    previewBusy = false;
    if (previewAgain) { previewAgain = false; preview(); }
  }
}

async function render() {
  showError("");
  const body = { values: state.values, size: Number($("render-size").value), spp: Number($("render-spp").value) };
  try {
    const { job } = await api("/api/render", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) });
    state.renderJob = job;
    $("render-cancel").disabled = false;
    for (;;) {
      const answer = await api(`/api/jobs/${job}`);
      $("render-bar").style.width = `${Math.round(100 * answer.progress)}%`;
      if (answer.state === "done") {
        $("render").src = answer.result.picture;
        $("render-note").textContent = `${answer.result.size} px, ${answer.result.spp} spp, ${answer.result.seconds.toFixed(1)} s`;
        break;
      }
      if (answer.state === "cancelled") { $("render-note").textContent = "cancelled"; break; }
      if (answer.state === "error") { showError(answer.error); break; }
      $("render-note").textContent = answer.stage;
      await new Promise((resolve) => setTimeout(resolve, 100));
    }
  } catch (error) {
    showError(error.message);
  } finally {
    $("render-cancel").disabled = true;
    state.renderJob = null;
  }
}

async function loadParams(file) {
  showError("");
  const form = new FormData();
  form.append("params", file, file.name);
  try {
    const { values } = await api("/api/params", { method: "POST", body: form });
    state.init = values;
    $("init-note").textContent = `${file.name}: joins the candidates of the next fits`;
    setValues(values);
  } catch (error) {
    showError(error.message);
  }
}

// --- start-up ------------------------------------------------------------------------------------
async function main() {
  const info = await api("/api/parameters");
  state.parameters = info.parameters;
  state.presets = info.presets;
  buildSliders();
  for (const name of Object.keys(info.presets)) addOption(name, name);
  setValues(info.parameters.map((p) => p.default));
  $("start").addEventListener("change", () => {
    const choice = $("start").value;
    if (choice === "__last" && state.lastFit) setValues(state.lastFit);
    else if (state.presets[choice]) setValues(state.presets[choice]);
  });
  $("picture").addEventListener("change", () => { if ($("picture").files[0]) fitFile($("picture").files[0]); $("picture").value = ""; });
  $("params-file").addEventListener("change", () => { if ($("params-file").files[0]) loadParams($("params-file").files[0]); $("params-file").value = ""; });
  const drop = $("drop");
  drop.addEventListener("dragover", (event) => { event.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (event) => { event.preventDefault(); drop.classList.remove("over"); if (event.dataTransfer.files[0]) fitFile(event.dataTransfer.files[0]); });
  $("render-button").addEventListener("click", render);
  const view = $("mask-view");
  view.addEventListener("pointerdown", (event) => { mask.painting = true; view.setPointerCapture(event.pointerId); paint(event); });
  view.addEventListener("pointermove", paint);
  view.addEventListener("pointerup", () => { mask.painting = false; });
  $("mask-clear").addEventListener("click", clearMask);
  $("mask-fit").addEventListener("click", fitWithMask);
  $("render-cancel").addEventListener("click", () => { if (state.renderJob) fetch(`/api/jobs/${state.renderJob}/cancel`, { method: "POST" }); });
  if (info.watch) {
    $("watching").textContent = `watching ${info.watch}`;
    const events = new EventSource("/api/watch");
    events.onmessage = (event) => {
      const message = JSON.parse(event.data);
      showError("");
      follow(message.job, message.file);
    };
  }
  document.body.dataset.ready = "yes";
}
main().catch((error) => showError(error.message));

// The EVA avatar service's page: plain JavaScript over the REST API (no build step, no CDN).
"use strict";

const POSE_SIZE = { width: 360, height: 420 };
const POLL_MS = 1000;
// While a slider moves, each render is a preview: half the size, JPEG (a quarter of the pixels to
// draw and no PNG to encode); once the sliders rest for SETTLE_MS, the full image follows.
const PREVIEW = { width: POSE_SIZE.width / 2, height: POSE_SIZE.height / 2, format: "jpeg" };
const SETTLE_MS = 120; // as long as the debounce before previews: the full image comes as soon

const state = {
  key: sessionStorage.getItem("eva-api-key"),
  keyPrompt: null, // a pending promise while the key dialog is open
  avatars: [],
  selected: null, // avatar id
  controls: [],
  framing: null,
  values: {},
  thumbnails: new Map(), // avatar id -> object URL
  jobs: new Map(), // job id -> {kind, label, avatarId, animationId, info}
  rendering: false,
  dirty: false, // the sliders changed since the last request was sent
  moving: false, // a slider moved in the last SETTLE_MS
  sharp: false, // the image shown is the full render of the sliders
  settleTimer: null,
  poseUrl: null,
  animationUrl: null,
  animationId: null,
};

const $ = (id) => document.getElementById(id);

// -- API calls, with the key when the service wants one -----------------------------------------
// A busy service answers 503 with Retry-After (renders at once, requests in flight): wait and
// retry a few times when it asks for a short wait; a long one (the job quota) is shown as is.
const BUSY_RETRIES = 3, BUSY_MAX_WAIT_S = 5;

async function api(path, options = {}, retries = BUSY_RETRIES) {
  const headers = new Headers(options.headers || {});
  if (state.key) headers.set("X-API-Key", state.key);
  const res = await fetch(path, { ...options, headers });
  if (res.status === 401) {
    await askForKey(Boolean(state.key));
    return api(path, options, retries);
  }
  const wait = Number(res.headers.get("Retry-After"));
  if (res.status === 503 && retries > 0 && wait > 0 && wait <= BUSY_MAX_WAIT_S) {
    await new Promise((resolve) => setTimeout(resolve, wait * 1000));
    return api(path, options, retries - 1);
  }
  return res;
}

function askForKey(refused) {
  // With a key the docs are behind it too, and a link cannot send the header: hide it.
  document.querySelector("a.docs").hidden = true;
  if (!state.keyPrompt) {
    state.keyPrompt = new Promise((resolve) => {
      const dialog = $("key-dialog");
      $("key-error").hidden = !refused;
      $("key-input").value = "";
      $("key-form").onsubmit = () => {
        state.key = $("key-input").value.trim();
        sessionStorage.setItem("eva-api-key", state.key);
        state.keyPrompt = null;
        resolve();
      };
      dialog.showModal();
    });
  }
  return state.keyPrompt;
}

async function errorText(res) {
  try {
    const body = await res.json();
    if (typeof body.detail === "string") return body.detail;
    if (Array.isArray(body.detail)) return body.detail.map((e) => `${(e.loc || []).join(".")}: ${e.msg}`).join("; ");
  } catch (_) { /* not JSON */ }
  return `HTTP ${res.status}`;
}

async function download(path, filename, button) {
  button.disabled = true;
  try {
    const res = await api(path);
    if (!res.ok) throw new Error(await errorText(res));
    const url = URL.createObjectURL(await res.blob());
    const a = document.createElement("a");
    a.href = url;
    a.download = filename;
    document.body.appendChild(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 10000);
  } catch (err) {
    alert(`Download failed: ${err.message}`);
  } finally {
    button.disabled = false;
  }
}

function formatSeconds(s) {
  if (s == null || !isFinite(s)) return "";
  if (s < 90) return `${Math.round(s)} s`;
  return `${Math.floor(s / 60)} min ${Math.round(s % 60)} s`;
}

// -- jobs: avatars and animations being made ------------------------------------------------------
function trackJob(jobId, job) {
  if (!state.jobs.has(jobId)) state.jobs.set(jobId, job);
  showJobs();
}

function showJobs() {
  const list = $("jobs");
  list.replaceChildren();
  if (state.jobs.size === 0) {
    list.innerHTML = '<li class="empty">No job running.</li>';
    return;
  }
  for (const [jobId, job] of state.jobs) {
    const info = job.info || { state: "queued", progress: 0 };
    const li = document.createElement("li");
    li.className = `job ${info.state}`;
    li.dataset.jobId = jobId;
    const eta = info.state === "running" && info.eta_seconds ? ` · about ${formatSeconds(info.eta_seconds)} left` : "";
    const stage = info.stage && info.state === "running" ? ` · ${info.stage}` : "";
    li.innerHTML = `<div class="what"><span class="label"></span><span class="state">${info.state}${stage}</span></div>
      <progress max="1"></progress>
      <div class="message"><span class="percent">${Math.round(100 * (info.progress || 0))}%</span>${eta} <span class="text"></span></div>`;
    li.querySelector(".label").textContent = job.label;
    li.querySelector("progress").value = info.progress || 0;
    li.querySelector(".text").textContent = info.error || info.message || "";
    list.appendChild(li);
  }
}

async function pollJobs() {
  for (const [jobId, job] of state.jobs) {
    if (job.info && ["succeeded", "failed", "cancelled"].includes(job.info.state)) continue;
    const res = await api(`/jobs/${jobId}`);
    if (!res.ok) continue;
    job.info = await res.json();
    if (job.info.state === "succeeded") onJobDone(job);
    if (["failed", "cancelled"].includes(job.info.state)) refreshAvatars();
  }
  showJobs();
}

async function onJobDone(job) {
  if (job.kind === "avatar") {
    await refreshAvatars();
    if (!state.selected) selectAvatar(job.avatarId);
  } else if (job.kind === "animation" && job.avatarId === state.selected) {
    showAnimation(job.animationId);
  }
}

// -- avatars ---------------------------------------------------------------------------------------
async function refreshAvatars() {
  const res = await api("/avatars");
  if (!res.ok) return;
  state.avatars = (await res.json()).avatars;
  for (const a of state.avatars) {
    if (a.status === "pending") trackJob(a.job_id, { kind: "avatar", label: `Avatar from ${a.source_video || "a video"}`, avatarId: a.avatar_id });
  }
  showAvatars();
}

// The held-out PSNR (frames training never saw) when the avatar has one: the training frames'
// own fit says little about new poses.
function cardScore(a) {
  const held = a.quality && a.quality.held_out;
  if (held && held.psnr != null) return ` · PSNR ${held.psnr.toFixed(1)} dB on unseen poses`;
  if (a.metrics && a.metrics.psnr) return ` · PSNR ${a.metrics.psnr.toFixed(1)} dB on training frames`;
  return "";
}

function showAvatars() {
  const list = $("avatars");
  list.replaceChildren();
  if (state.avatars.length === 0) {
    list.innerHTML = '<li class="empty">No avatar yet: upload a video.</li>';
    return;
  }
  for (const a of [...state.avatars].reverse()) {
    const li = document.createElement("li");
    li.className = "avatar-card" + (a.avatar_id === state.selected ? " selected" : "");
    li.dataset.avatarId = a.avatar_id;
    li.dataset.status = a.status;
    const thumb = state.thumbnails.get(a.avatar_id);
    const gaussians = a.num_gaussians ? `${a.num_gaussians.toLocaleString()} Gaussians` : "";
    const psnr = cardScore(a);
    li.innerHTML = `${thumb ? `<img alt="">` : '<div class="placeholder"></div>'}
      <div><div class="name"></div><div class="facts">${a.status}${a.preset ? ` · ${a.preset}` : ""}</div>
      <div class="facts">${gaussians}${psnr}</div></div>`;
    if (thumb) li.querySelector("img").src = thumb;
    li.querySelector(".name").textContent = a.source_video || a.avatar_id.slice(0, 8);
    const verdict = a.quality && a.quality.verdict;
    if (verdict) {
      // The verdict as a badge; its reasons in words under it (and on hover).
      const badge = document.createElement("span");
      badge.className = `badge quality-${verdict}`;
      badge.textContent = verdict;
      badge.title = (a.quality.reasons || []).join("\n") || "no concerns";
      li.querySelector(".name").append(" ", badge);
      if (verdict !== "good" && a.quality.reasons && a.quality.reasons.length) {
        const why = document.createElement("ul");
        why.className = "reasons";
        for (const r of a.quality.reasons) {
          const item = document.createElement("li");
          item.textContent = r;
          why.appendChild(item);
        }
        li.lastElementChild.appendChild(why);
      }
    }
    if (a.status === "ready") {
      li.addEventListener("click", () => selectAvatar(a.avatar_id));
      if (!thumb) loadThumbnail(a);
    } else if (a.error) {
      li.querySelector(".facts").textContent += `: ${a.error}`;
    }
    list.appendChild(li);
  }
}

async function loadThumbnail(avatar) {
  state.thumbnails.set(avatar.avatar_id, ""); // once
  // A training frame in its own camera: framed as the video was.
  const body = avatar.num_frames ? { frame: Math.floor(avatar.num_frames / 2), width: 128 } : { width: 128, height: 128 };
  const res = await api(`/avatars/${avatar.avatar_id}/render`, {
    method: "POST", headers: { "content-type": "application/json" }, body: JSON.stringify({ ...body, format: "jpeg" }),
  });
  if (!res.ok) return;
  const url = URL.createObjectURL(await res.blob());
  state.thumbnails.set(avatar.avatar_id, url);
  // In place: rebuilding the list would pull a card from under a click.
  const placeholder = document.querySelector(`.avatar-card[data-avatar-id="${avatar.avatar_id}"] .placeholder`);
  if (placeholder) {
    const img = document.createElement("img");
    img.alt = "";
    img.src = url;
    placeholder.replaceWith(img);
  }
}

async function selectAvatar(avatarId) {
  state.selected = avatarId;
  showAvatars();
  const avatar = state.avatars.find((a) => a.avatar_id === avatarId);
  $("pose-title").textContent = `(${avatar ? avatar.source_video || avatarId.slice(0, 8) : avatarId.slice(0, 8)})`;
  $("pose-status").textContent = "Loading the sliders...";
  const res = await api(`/avatars/${avatarId}/controls?aspect=${POSE_SIZE.width / POSE_SIZE.height}`);
  if (!res.ok) {
    $("pose-status").textContent = await errorText(res);
    return;
  }
  const doc = await res.json();
  state.controls = doc.controls;
  state.framing = doc.framing;
  state.values = {};
  buildSliders();
  for (const id of ["download-ply", "download-glb", "animate-button"]) $(id).disabled = false;
  $("animation-video").hidden = true;
  $("download-mp4").disabled = true;
  renderPose();
  showLatestAnimation(avatarId);
}

// -- posing: sliders -> pose JSON -> the render endpoint -----------------------------------------
function buildSliders() {
  const box = $("control-groups");
  box.replaceChildren();
  const groups = new Map();
  for (const c of state.controls) {
    if (!groups.has(c.group)) {
      const fs = document.createElement("fieldset");
      fs.className = "group";
      fs.innerHTML = "<legend></legend>";
      fs.querySelector("legend").textContent = c.group;
      groups.set(c.group, fs);
      box.appendChild(fs);
    }
    const label = document.createElement("label");
    label.innerHTML = `<span></span><input type="range"><output></output>`;
    label.querySelector("span").textContent = c.label;
    const input = label.querySelector("input");
    Object.assign(input, { min: c.min, max: c.max, step: (c.max - c.min) / 100, value: c.value });
    input.dataset.control = c.name;
    const output = label.querySelector("output");
    output.textContent = Number(c.value).toFixed(2);
    input.addEventListener("input", () => {
      state.values[c.name] = Number(input.value);
      output.textContent = Number(input.value).toFixed(2);
      scheduleRender();
    });
    groups.get(c.group).appendChild(label);
  }
  if (state.controls.length === 0) box.innerHTML = '<p class="muted">This body model has no sliders.</p>';
}

function quatFromAxisAngle(axis, angle) {
  const s = Math.sin(angle / 2);
  return [Math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s];
}

function quatMultiply(a, b) {
  return [
    a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
    a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
    a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
    a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
  ];
}

function quatToRotvec(q) {
  const sign = q[0] < 0 ? -1 : 1; // the shorter way round
  const [w, x, y, z] = q.map((v) => v * sign);
  const s = Math.hypot(x, y, z);
  if (s < 1e-9) return [2 * x, 2 * y, 2 * z];
  const k = (2 * Math.atan2(s, w)) / s;
  return [x * k, y * k, z * k];
}

// The pose of the sliders: a joint's rotation is the product (in list order) of its controls'
// rotations; an expression the sum of its controls' weights (GET /avatars/{id}/controls).
function poseFromSliders() {
  const rotations = new Map();
  const expression = {};
  for (const c of state.controls) {
    const v = state.values[c.name] || 0;
    if (v === 0) continue;
    for (const t of c.joints) {
      const q = quatFromAxisAngle(t.axis, v * t.gain);
      rotations.set(t.joint, rotations.has(t.joint) ? quatMultiply(rotations.get(t.joint), q) : q);
    }
    for (const t of c.expressions) expression[t.expression] = Math.min(1, (expression[t.expression] || 0) + v * t.gain);
  }
  const joints = {};
  for (const [name, q] of rotations) joints[name] = quatToRotvec(q);
  return { joints, expression };
}

function zoom() {
  return 2 ** Number($("camera-zoom").value); // -1..1: half to twice as close
}

function cameraFromSliders() {
  const camera = { yaw: Number($("camera-yaw").value), pitch: Number($("camera-pitch").value) };
  if (state.framing) {
    Object.assign(camera, { target: state.framing.target, distance: state.framing.distance / zoom(), fov_y: state.framing.fov_y });
  }
  return camera;
}

function showCamera() {
  $("camera-yaw").nextElementSibling.textContent = `${$("camera-yaw").value}°`;
  $("camera-pitch").nextElementSibling.textContent = `${$("camera-pitch").value}°`;
  $("camera-zoom").nextElementSibling.textContent = `${zoom().toFixed(2)}×`;
}

// A slider moved: render the new pose as soon as the request in flight is back (one at a time,
// the latest sliders win), as previews while the sliders keep moving.
function scheduleRender() {
  state.dirty = true;
  state.moving = true;
  clearTimeout(state.settleTimer);
  state.settleTimer = setTimeout(() => {
    state.moving = false;
    renderPose();
  }, SETTLE_MS);
  renderPose();
}

// A pose or view beyond what the training video showed still renders; the service says so.
function showWarnings(header) {
  const list = $("pose-warnings");
  let warnings = [];
  try {
    warnings = header ? JSON.parse(header) : [];
  } catch {
    warnings = [];
  }
  list.replaceChildren(...warnings.map((text) => {
    const li = document.createElement("li");
    li.textContent = `Outside what the video showed: ${text}.`;
    return li;
  }));
  list.hidden = warnings.length === 0;
}

async function renderPose() {
  if (!state.selected) return;
  if (state.rendering) { // one request at a time: the one in flight calls again when back
    state.dirty = true;
    return;
  }
  const preview = state.moving;
  state.rendering = true;
  state.dirty = false;
  const avatarId = state.selected;
  const img = $("pose-image");
  img.classList.add("busy");
  const started = performance.now();
  try {
    const body = { pose: poseFromSliders(), camera: cameraFromSliders(), ...(preview ? PREVIEW : POSE_SIZE) };
    const res = await api(`/avatars/${avatarId}/render`, {
      method: "POST", headers: { "content-type": "application/json" }, body: JSON.stringify(body),
    });
    if (!res.ok) {
      state.sharp = true; // nothing better to show until a slider moves again: no retry loop
      $("pose-status").textContent = await errorText(res);
      return;
    }
    showWarnings(res.headers.get("X-Render-Warnings"));
    const url = URL.createObjectURL(await res.blob());
    await new Promise((resolve) => {
      img.onload = resolve;
      img.onerror = resolve;
      img.src = url;
    });
    if (state.poseUrl) URL.revokeObjectURL(state.poseUrl);
    state.poseUrl = url;
    state.sharp = !preview && !state.dirty;
    img.dataset.detail = preview ? "preview" : "full";
    img.dataset.renders = String(Number(img.dataset.renders) + 1);
    $("pose-status").textContent = `Rendered in ${Math.round(performance.now() - started)} ms. Move a slider to pose the avatar.`;
  } catch (err) {
    state.sharp = true;
    $("pose-status").textContent = `Render failed: ${err.message}`;
  } finally {
    img.classList.remove("busy");
    state.rendering = false;
    if (state.selected && (state.dirty || (!state.moving && !state.sharp))) renderPose();
  }
}

// -- animation -------------------------------------------------------------------------------------
async function showAnimation(animationId) {
  const res = await api(`/animations/${animationId}`);
  if (!res.ok) return;
  const info = await res.json();
  if (!info.video_url) return;
  const video = await api(info.video_url);
  if (!video.ok) return;
  if (state.animationUrl) URL.revokeObjectURL(state.animationUrl);
  state.animationUrl = URL.createObjectURL(await video.blob());
  state.animationId = animationId;
  const player = $("animation-video");
  player.src = state.animationUrl;
  player.dataset.animationId = animationId;
  player.hidden = false;
  player.play().catch(() => {});
  $("download-mp4").disabled = false;
}

async function showLatestAnimation(avatarId) {
  const res = await api(`/avatars/${avatarId}/animations`);
  if (!res.ok) return;
  const done = (await res.json()).animations.filter((a) => a.state === "succeeded");
  if (done.length && state.selected === avatarId) showAnimation(done[done.length - 1].animation_id);
}

// -- forms -----------------------------------------------------------------------------------------
function addNumber(form, name, input) {
  if (input.value !== "") form.append(name, input.value);
}

async function uploadVideo(event) {
  event.preventDefault();
  const file = $("video-input").files[0];
  const error = $("upload-error");
  error.hidden = true;
  if (!file) return;
  const form = new FormData();
  form.append("video", file, file.name);
  if ($("preset").value) form.append("preset", $("preset").value);
  if ($("method").value) form.append("method", $("method").value);
  addNumber(form, "iterations", $("iterations"));
  addNumber(form, "image_scale", $("image-scale"));
  addNumber(form, "max_frames", $("max-frames"));
  addNumber(form, "max_size", $("max-size"));
  addNumber(form, "fit_scale", $("fit-scale"));
  if ($("face-closeups").checked) form.append("face_closeups", "true");
  $("upload-button").disabled = true;
  try {
    const res = await api("/avatars", { method: "POST", body: form });
    if (!res.ok) throw new Error(await errorText(res));
    const created = await res.json();
    trackJob(created.job_id, { kind: "avatar", label: `Avatar from ${file.name}`, avatarId: created.avatar_id });
    $("upload-form").reset();
    refreshAvatars();
  } catch (err) {
    error.textContent = err.message;
    error.hidden = false;
  } finally {
    $("upload-button").disabled = false;
  }
}

async function animateAvatar(event) {
  event.preventDefault();
  const file = $("driving-input").files[0];
  const error = $("animate-error");
  error.hidden = true;
  if (!file || !state.selected) return;
  const isPoses = file.name.toLowerCase().endsWith(".json");
  const form = new FormData();
  form.append(isPoses ? "poses" : "video", file, file.name);
  form.append("camera", isPoses && $("animate-camera").value === "driving" ? "front" : $("animate-camera").value);
  form.append("side_by_side", String($("side-by-side").checked && !isPoses));
  addNumber(form, "fps", $("animate-fps"));
  addNumber(form, "max_frames", $("animate-max-frames"));
  addNumber(form, "fit_scale", $("animate-fit-scale"));
  $("animate-button").disabled = true;
  try {
    const res = await api(`/avatars/${state.selected}/animations`, { method: "POST", body: form });
    if (!res.ok) throw new Error(await errorText(res));
    const created = await res.json();
    trackJob(created.job_id, {
      kind: "animation", label: `Animation with ${file.name}`, avatarId: state.selected, animationId: created.animation_id,
    });
  } catch (err) {
    error.textContent = err.message;
    error.hidden = false;
  } finally {
    $("animate-button").disabled = !state.selected;
  }
}

function resetPose() {
  state.values = {};
  for (const input of document.querySelectorAll("#control-groups input[type=range]")) {
    input.value = 0;
    input.nextElementSibling.textContent = "0.00";
  }
  for (const id of ["camera-yaw", "camera-pitch", "camera-zoom"]) $(id).value = 0;
  showCamera();
  scheduleRender();
}

async function loadPageOptions() {
  // Public, like the page: no key. Without it the forms still work, unbounded, on the API's defaults.
  const res = await fetch("/page/options");
  if (res.ok) applyPageOptions(document, await res.json());
}

function init() {
  loadPageOptions();
  $("upload-form").addEventListener("submit", uploadVideo);
  $("animate-form").addEventListener("submit", animateAvatar);
  $("reset-pose").addEventListener("click", resetPose);
  for (const id of ["camera-yaw", "camera-pitch", "camera-zoom"]) {
    $(id).addEventListener("input", () => {
      showCamera();
      scheduleRender();
    });
  }
  $("download-ply").addEventListener("click", (e) => download(`/avatars/${state.selected}/export?format=ply`, `avatar-${state.selected}.ply`, e.target));
  $("download-glb").addEventListener("click", (e) => download(`/avatars/${state.selected}/export?format=glb`, `avatar-${state.selected}.glb`, e.target));
  $("download-mp4").addEventListener("click", (e) => download(`/animations/${state.animationId}/video`, `animation-${state.animationId}.mp4`, e.target));
  refreshAvatars();
  setInterval(pollJobs, POLL_MS);
}

document.addEventListener("DOMContentLoaded", init);

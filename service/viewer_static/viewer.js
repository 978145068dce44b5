// The Push-T viewer page: draws the states the service streams over /viewer/ws and sends the pointer while held.
(() => {
  "use strict";
  const query = new URLSearchParams(location.search);
  const $ = (id) => document.getElementById(id);
  const canvas = $("board");
  const ctx = canvas.getContext("2d");
  const TELEOP = "";  // the policy menu's value for "no policy"
  let ws = null;
  let goal = null;
  let last = null;  // the last state message
  let lastSaved = null;
  let lastError = null;
  let held = false;
  let started = false;
  let status = { step: 0, coverage: 0, maxReward: 0, done: false, success: false };

  function send(message) {
    if (ws && ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify(message));
  }

  function show(text) { $("message").textContent = text; }

  function connect() {
    if (ws) ws.close();
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    ws = new WebSocket(`${scheme}://${location.host}/viewer/ws`);
    ws.onopen = () => {
      const key = $("key").value || sessionStorage.getItem("pushtKey");
      send({ type: "hello", key: key || null });
    };
    ws.onmessage = (event) => receive(JSON.parse(event.data));
    ws.onclose = (event) => { $("status").textContent = `disconnected (${event.code})`; };
  }

  function receive(message) {
    if (message.type === "hello") {
      if ($("key").value) sessionStorage.setItem("pushtKey", $("key").value);
      goal = message.goal;
      const menu = $("policy");
      menu.innerHTML = "";
      for (const name of [...message.policies, TELEOP]) {
        const option = document.createElement("option");
        option.value = name;
        option.textContent = name === TELEOP ? "teleop (no policy)" : name;
        menu.appendChild(option);
      }
      const wanted = query.get("mode") === "teleop" ? TELEOP : query.get("policy");
      if (wanted !== null && [...menu.options].some((o) => o.value === wanted)) menu.value = wanted;
      if (query.has("seed")) $("seed").value = query.get("seed");
      if (query.has("fps")) $("fps").value = query.get("fps");
      show(message.saving ? "" : "saving is off on this service (PUSHT_VIEWER_DATA_DIR is unset)");
      draw();
      if (query.get("autoplay") === "1" && !started) start();
    } else if (message.type === "state") {
      last = message;
      status = { step: message.step, coverage: message.coverage, maxReward: message.maxReward, done: message.done, success: message.success };
      draw();
    } else if (message.type === "saved") {
      lastSaved = message;
      show(`saved ${message.steps} steps (${message.humanSteps} yours) as ${message.name}`);
    } else if (message.type === "error") {
      lastError = message;
      const detail = typeof message.detail === "string" ? message.detail : JSON.stringify(message.detail);
      show(`error ${message.status}: ${detail}`);
      if (message.status === 401) $("key").focus();
    }
  }

  function start() {
    started = true;
    lastSaved = null;
    const policy = $("policy").value;
    send({ type: "start", policy: policy === TELEOP ? null : policy, seed: Number($("seed").value), fps: Number($("fps").value) });
  }

  function polygon(points, fill) {
    ctx.beginPath();
    points.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.closePath();
    ctx.fillStyle = fill;
    ctx.fill();
  }

  function draw() {
    ctx.fillStyle = "#fff";
    ctx.fillRect(0, 0, 512, 512);
    ctx.strokeStyle = "#d3d3d3";
    ctx.lineWidth = 4;
    ctx.strokeRect(5, 5, 501, 501);
    if (goal) goal.forEach((rect) => polygon(rect, "#90ee90"));
    if (!last) return;
    last.block.forEach((rect) => polygon(rect, "#778899"));
    const [ax, ay] = last.state;
    ctx.beginPath();
    ctx.arc(ax, ay, 15, 0, 2 * Math.PI);
    ctx.fillStyle = last.actor === "human" ? "#ffa54f" : "#4e7eff";
    ctx.fill();
    if (last.action) {
      const [cx, cy] = last.action;
      ctx.strokeStyle = "#f00";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(cx - 6, cy); ctx.lineTo(cx + 6, cy); ctx.moveTo(cx, cy - 6); ctx.lineTo(cx, cy + 6);
      ctx.stroke();
    }
    const who = last.policy === null ? "teleop" : last.policy;
    const text = `step ${last.step}  coverage ${last.coverage.toFixed(3)}  max reward ${last.maxReward.toFixed(3)}` +
      `${last.success ? "  success" : ""}${last.done ? "  done" : ""}`;
    ctx.fillStyle = "#000";
    ctx.font = "14px sans-serif";
    ctx.fillText(text, 12, 26);
    $("status").textContent = `${who}, seed ${last.seed}: ${text}  (${last.humanSteps} steps yours)`;
  }

  function boardPoint(event) {
    const box = canvas.getBoundingClientRect();
    return { x: ((event.clientX - box.left) * canvas.width) / box.width, y: ((event.clientY - box.top) * canvas.height) / box.height };
  }

  canvas.addEventListener("pointerdown", (event) => {
    held = true;
    canvas.setPointerCapture(event.pointerId);
    send({ type: "pointer", ...boardPoint(event), down: true });
  });
  canvas.addEventListener("pointermove", (event) => { if (held) send({ type: "pointer", ...boardPoint(event), down: true }); });
  for (const name of ["pointerup", "pointercancel"]) {
    canvas.addEventListener(name, (event) => { held = false; send({ type: "pointer", ...boardPoint(event), down: false }); });
  }
  $("start").addEventListener("click", start);
  $("save").addEventListener("click", () => send({ type: "save" }));
  $("connect").addEventListener("click", connect);

  // Test hooks (and a console API): the score so far, start, save and what the service last said.
  window.pushtViewer = {
    status: () => ({ ...status }),
    start,
    save: () => { lastSaved = null; send({ type: "save" }); },
    lastSaved: () => lastSaved,
    lastError: () => lastError,
    connected: () => ws !== null && ws.readyState === WebSocket.OPEN && goal !== null,
  };
  draw();
  connect();
})();

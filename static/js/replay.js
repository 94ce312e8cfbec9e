// A trial replay file (static/replay.html, written by server/viewer/replay_page.py): viser's client plays the
// trial's recording in the iframe; the panel beside it lists the trial's moments and follows the player's time,
// which the recording itself posts (a line of JavaScript every 0.1 s of it: server/viewer/recording.py), so the
// timeline follows playing, pausing, looping and scrubbing alike. Nothing is fetched: the player, the recordings
// and this script are all in the file.
"use strict";

(() => {
  const data = JSON.parse(document.getElementById("replay-data").textContent);
  // the player's page is kept with its closing script tag escaped (it sits inside a script element here)
  const client = document.getElementById("viser-client").textContent.replace(/<\\\/script/g, "</script");
  const $ = (id) => document.getElementById(id);
  const PHASES = { announcement: "announcement", decision: "decision window", attempt: "robot's attempt",
    teleop: "teleoperation", done: "done" };
  let trial = null;
  let items = [];
  let currentIndex = -1;

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [name, value] of Object.entries(attrs || {})) node.setAttribute(name, value);
    node.append(...children);
    return node;
  }

  function show(index) {
    trial = data.trials[index];
    $("title").textContent = `${data.participant} · ${trial.label}`;
    $("subtitle").textContent = `study ${data.study} · ${trial.complexity} complexity · robot ${trial.robot_action}`;
    $("recorded").textContent = trial.recorded;
    $("reconstructed").replaceChildren(trial.reproduced
      ? el("span", { class: "ok" }, `the same: ${trial.reconstructed}`) : trial.reconstructed);
    $("missing").replaceChildren(...trial.missing.map((text) => el("div", {}, `${text[0].toUpperCase()}${text.slice(1)}.`)));
    $("duration").textContent = trial.duration.toFixed(1);
    const bar = $("bar");
    bar.querySelectorAll(".phase").forEach((node) => node.remove());
    const kinds = new Set();
    for (const phase of trial.phases) {
      kinds.add(phase.kind);
      const left = (100 * phase.start) / trial.duration;
      const width = (100 * Math.max(0, phase.end - phase.start)) / trial.duration;
      bar.prepend(el("div", { class: `phase phase-${phase.kind}`, title: PHASES[phase.kind] || phase.kind,
        style: `left:${left}%;width:${width}%` }));
    }
    $("legend").replaceChildren(...[...kinds].map((kind) => el("span", {}, el("i", { class: `phase-${kind}` }),
      PHASES[kind] || kind)));
    items = trial.moments.map((m) => el("li", { class: `kind-${m.kind}`, "data-t": String(m.t) },
      el("time", {}, m.t.toFixed(1)), el("span", {}, m.text)));
    $("moments").replaceChildren(...items);
    currentIndex = -1;
    setTime(0);
    // viser's client reads the recording from a global set before it starts (as viser's own as_html writes it)
    const embed = `<script>window.__VISER_EMBED_DATA__="${trial.recording}";`
      + "window.__VISER_EMBED_CONFIG__={darkMode:false};</script>";
    $("player").srcdoc = client.replace("</head>", () => `${embed}</head>`);
  }

  function setTime(t) {
    if (!trial) return;
    $("marker").style.left = `${(100 * Math.min(t, trial.duration)) / trial.duration}%`;
    $("now").textContent = t.toFixed(1);
    document.body.dataset.replayTime = t.toFixed(3);
    let current = -1;
    items.forEach((item, i) => {
      const past = Number(item.dataset.t) <= t + 1e-6;
      item.classList.toggle("past", past);
      if (past) current = i;
    });
    if (current !== currentIndex) {
      if (currentIndex >= 0) items[currentIndex].classList.remove("current");
      if (current >= 0) {
        items[current].classList.add("current");
        items[current].scrollIntoView({ block: "nearest" });
      }
      currentIndex = current;
    }
  }

  window.addEventListener("message", (event) => {
    if (event.source !== $("player").contentWindow) return;
    const t = event.data && event.data.trustlabReplayTime;
    if (typeof t === "number" && Number.isFinite(t)) setTime(t);
  });

  if (data.trials.length > 1) {
    $("trial-choice").hidden = false;
    data.trials.forEach((t, i) => $("trial").append(el("option", { value: String(i) },
      `${t.label}${t.reproduced ? "" : " (incomplete)"}`)));
    $("trial").addEventListener("change", () => show(Number($("trial").value)));
  }
  const wanted = Number(new URLSearchParams(window.location.hash.slice(1)).get("trial"));
  const first = Number.isInteger(wanted) && wanted >= 0 && wanted < data.trials.length ? wanted : 0;
  $("trial").value = String(first);
  show(first);
})();

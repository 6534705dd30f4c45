// Plays an exported .glb (morph targets + skin + one animation) in sync with the .wav beside it.
//
// The audio clock drives the animation: every frame the mixer is set to the audio's currentTime, so
// picture and sound cannot drift apart. `?clip=NAME` picks a clip; `?t=SECONDS` shows a still frame at
// that time with no controls (what the browser test photographs) and sets `window.jaxtalkReady`.
// While playing, `window.jaxtalkClock()` reports the audio clock and the time last drawn (for tests).
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { stage } from "/stage.js";

const query = new URLSearchParams(location.search);
const still = query.has("t") ? Number(query.get("t")) : null;
const status = document.getElementById("status");
const playButton = document.getElementById("play");
const picker = document.getElementById("clip");

const clips = await (await fetch("/clips.json")).json();
if (clips.length === 0) {
  status.textContent = "no .glb files in this folder";
  throw new Error("no clips");
}
const clip = clips.find((c) => c.name === query.get("clip")) ?? clips[0];
for (const c of clips) picker.add(new Option(c.name, c.name, false, c === clip));
picker.onchange = () => { query.set("clip", picker.value); location.search = query.toString(); };

const gltf = await new GLTFLoader().loadAsync(clip.glb);
const { renderer, draw } = stage(document.getElementById("scene"), gltf.scene);

const animation = gltf.animations[0];
const mixer = new THREE.AnimationMixer(gltf.scene);
const action = mixer.clipAction(animation);
action.setLoop(THREE.LoopOnce);
action.clampWhenFinished = true;
action.play();

if (still !== null) {
  document.body.classList.add("still");
  mixer.setTime(Math.min(Math.max(still, 0), animation.duration));
  draw();
  // Two animation frames: the canvas is composited before a screenshot is taken.
  requestAnimationFrame(() => requestAnimationFrame(() => { window.jaxtalkReady = true; }));
} else {
  const audio = clip.audio ? new Audio(clip.audio) : null;
  // Without audio, a wall clock that pauses: `offset` seconds played before `startedAt`.
  let offset = 0, startedAt = null;
  const time = () => (audio ? audio.currentTime : offset + (startedAt === null ? 0 : (performance.now() - startedAt) / 1000));
  const playing = () => (audio ? !audio.paused && !audio.ended : startedAt !== null);
  let shown = 0;
  window.jaxtalkClock = () => ({ audio: audio ? audio.currentTime : null, shown, playing: playing() });
  const stop = () => { if (audio) audio.pause(); else if (startedAt !== null) { offset = time(); startedAt = null; } };
  playButton.disabled = false;
  playButton.onclick = async () => {
    if (playing()) stop();
    else {
      if (time() >= animation.duration) { if (audio) audio.currentTime = 0; else offset = 0; }
      if (audio) await audio.play(); else startedAt = performance.now();
    }
  };
  renderer.setAnimationLoop(() => {
    if (!audio && time() >= animation.duration) stop();
    const t = Math.min(time(), animation.duration);
    mixer.setTime(t);
    shown = t;
    draw();
    playButton.textContent = playing() ? "Pause" : "Play";
    status.textContent = `${clip.name}  ${t.toFixed(2)} / ${animation.duration.toFixed(2)} s${audio ? "" : "  (no audio)"}`;
  });
  window.jaxtalkReady = true;
}

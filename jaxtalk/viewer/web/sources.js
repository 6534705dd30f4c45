// The audio both live pages stream (`jaxtalk view --live` and the page `jaxtalk export-model` writes): the
// microphone or a file, through the capture worklet (capture.js: mono at `rate`, posted in blocks of `block`
// samples), driven by the page's Microphone, Play a file and Stop buttons.
//
// audioInput({ rate, block, worklet, buttons, onBlock, onStart, onStop, fail }) wires the buttons and returns
// { startMicrophone, stop }: `onBlock(samples)` gets every block, `onStart()` runs once audio flows, `onStop()`
// once it has stopped (a file that ends stops by itself).
export function audioInput({ rate, block, worklet, buttons, onBlock, onStart, onStop, fail }) {
  let audio = null; // {context, halt}

  async function start(connect) {
    await stop();
    let context;
    try { context = new AudioContext({ sampleRate: rate }); } catch { context = new AudioContext(); }
    await context.audioWorklet.addModule(worklet);
    const node = new AudioWorkletNode(context, "jaxtalk-capture", { numberOfInputs: 1, numberOfOutputs: 1, channelCount: 1,
                                                                    channelCountMode: "explicit",
                                                                    processorOptions: { targetRate: rate, block } });
    node.port.onmessage = (e) => onBlock(e.data);
    const sink = context.createGain();
    sink.gain.value = 0; // the worklet runs only when pulled: through a silent gain to the speakers
    node.connect(sink).connect(context.destination);
    const halt = await connect(context, node);
    await context.resume();
    audio = { context, halt };
    onStart();
    buttons.stop.disabled = false;
  }

  async function stop() {
    if (!audio) return;
    audio.halt();
    await audio.context.close();
    audio = null;
    onStop();
    buttons.stop.disabled = true;
  }

  async function startMicrophone() {
    await start(async (context, node) => {
      const stream = await navigator.mediaDevices.getUserMedia({ audio: { channelCount: 1, echoCancellation: false,
                                                                           noiseSuppression: false, autoGainControl: false } });
      context.createMediaStreamSource(stream).connect(node);
      return () => stream.getTracks().forEach((t) => t.stop());
    });
  }

  async function playFile(file) {
    await start(async (context, node) => {
      const buffer = await context.decodeAudioData(await file.arrayBuffer());
      const source = context.createBufferSource();
      source.buffer = buffer;
      source.connect(node);
      source.connect(context.destination); // and heard
      source.onended = () => stop().catch(fail);
      source.start();
      return () => { source.onended = null; try { source.stop(); } catch { /* already ended */ } };
    });
  }

  buttons.mic.onclick = () => startMicrophone().catch(fail);
  buttons.file.onchange = () => { if (buttons.file.files[0]) playFile(buttons.file.files[0]).catch(fail); };
  buttons.stop.onclick = () => stop().catch(fail);
  return { startMicrophone, stop };
}

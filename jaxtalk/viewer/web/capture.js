// AudioWorklet of `jaxtalk view --live`: mono audio at the context's rate -> 16-kHz float blocks for the server.
//
// Each input block (128 frames) is mixed to mono, resampled to `targetRate` (linear interpolation after a
// moving-average low-pass when the context runs faster: 48 kHz -> 16 kHz averages 3 samples) and appended
// to a buffer; every `block` output samples the buffer is posted to the page, which stamps it with its
// capture time and sends it.
class Capture extends AudioWorkletProcessor {
  constructor(options) {
    super();
    const { targetRate, block } = options.processorOptions;
    this.step = sampleRate / targetRate; // input samples per output sample
    this.width = Math.max(1, Math.round(this.step)); // low-pass: average this many input samples
    this.block = block;
    this.out = new Float32Array(block);
    this.filled = 0;
    this.sum = 0;
    this.ring = new Float32Array(this.width);
    this.ringAt = 0;
    this.read = 0; // position of the next output sample, in input samples since the previous block's end
    this.last = 0; // the previous block's last filtered sample
  }

  emit(value) {
    this.out[this.filled++] = value;
    if (this.filled === this.block) {
      this.port.postMessage(this.out);
      this.out = new Float32Array(this.block);
      this.filled = 0;
    }
  }

  process(inputs) {
    const input = inputs[0];
    if (!input || input.length === 0 || input[0].length === 0) return true;
    const n = input[0].length;
    const filtered = new Float32Array(n);
    for (let i = 0; i < n; i++) {
      let x = 0;
      for (let c = 0; c < input.length; c++) x += input[c][i];
      x /= input.length;
      if (this.width === 1) {
        filtered[i] = x;
      } else {
        this.sum += x - this.ring[this.ringAt];
        this.ring[this.ringAt] = x;
        this.ringAt = (this.ringAt + 1) % this.width;
        filtered[i] = this.sum / this.width;
      }
    }
    if (this.step === 1) {
      for (let i = 0; i < n; i++) this.emit(filtered[i]);
      return true;
    }
    // Output sample at input position p (p = -1 is the previous block's last sample).
    while (this.read < n - 1) {
      const p = this.read;
      const i = Math.floor(p);
      const a = i < 0 ? this.last : filtered[i];
      const b = filtered[i + 1];
      this.emit(a + (b - a) * (p - i));
      this.read += this.step;
    }
    this.read -= n;
    this.last = filtered[n - 1];
    return true;
  }
}

registerProcessor("jaxtalk-capture", Capture);

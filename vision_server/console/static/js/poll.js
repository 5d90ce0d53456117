// Repeating work while a page is visible: a round starts every ``intervalMs`` (a live view at its
// frame-rate cap), or as soon as the previous one finished when that took longer: never two at
// once, so a slow server is not piled up with requests.

export class Poller {
  constructor(fn, intervalMs) {
    this.fn = fn;
    this.intervalMs = intervalMs;
    this.timer = null;
    this.running = false;
    this.generation = 0;
  }

  start() {
    if (this.running) return;
    this.running = true;
    this.generation += 1;
    this.round(this.generation);
  }

  stop() {
    this.running = false;
    clearTimeout(this.timer);
    this.timer = null;
  }

  /** Run now (for example after a filter changed), then keep the rhythm. */
  kick() {
    if (!this.running) return;
    clearTimeout(this.timer);
    this.generation += 1;
    this.round(this.generation);
  }

  async round(generation) {
    const started = performance.now();
    try {
      await this.fn();
    } catch (exc) {
      // The page shows its own errors; a failed round must not end the polling.
      console.warn("console: poll failed", exc);
    }
    if (this.running && generation === this.generation) {
      const wait = Math.max(0, this.intervalMs - (performance.now() - started));
      this.timer = setTimeout(() => this.round(generation), wait);
    }
  }
}

// Alarm tones in the browser, timed as IEC 60601-1-8 describes auditory alarm signals.
//
// High: a burst of 10 pulses in groups of 3 + 2 + 3 + 2, repeated; medium: 3 pulses; low: 2 pulses, repeated
// only after more than 15 s. Each pulse is a fundamental in 150-1000 Hz with four harmonics (300-4000 Hz), so
// it can be located and heard over ward noise, and ramps in and out so it does not click.
// toneSchedule() is pure, so a test can check the timing against the standard's ranges and against the bedside
// buzzer's schedule (appliance/alerts/tones.py), which has the same numbers.
"use strict";

const TONES = {
  // pulse length, silence between pulses in a group, extra silence between groups, group sizes, silence after
  // the burst before it repeats (ms), fundamental (Hz)
  high: {pulseMs: 150, spaceMs: 100, groupGapMs: [350, 700, 350], groups: [3, 2, 3, 2], restMs: 5000, hz: 523},
  medium: {pulseMs: 200, spaceMs: 200, groupGapMs: [], groups: [3], restMs: 10000, hz: 440},
  low: {pulseMs: 200, spaceMs: 200, groupGapMs: [], groups: [2], restMs: 20000, hz: 392},
};
const HARMONICS = 5;             // the fundamental and four harmonics

// {pulses: [{startMs, lengthMs}], hz, harmonicsHz, burstMs, restMs, periodMs} for "high", "medium" or "low".
function toneSchedule(priority) {
  const tone = TONES[priority];
  if (!tone) throw new Error(`no alarm tone for priority ${JSON.stringify(priority)}: high, medium or low`);
  const pulses = [];
  let at = 0;
  tone.groups.forEach((size, g) => {
    for (let k = 0; k < size; k++) {
      pulses.push({startMs: at, lengthMs: tone.pulseMs});
      at += tone.pulseMs + tone.spaceMs;
    }
    if (g < tone.groupGapMs.length) at += tone.groupGapMs[g];
  });
  const burstMs = at - tone.spaceMs;
  const harmonicsHz = Array.from({length: HARMONICS}, (_, n) => tone.hz * (n + 1));
  return {pulses, hz: tone.hz, harmonicsHz, burstMs, restMs: tone.restMs, periodMs: burstMs + tone.restMs};
}

// Plays one priority's bursts, over and over, until set to another or to null. Browsers allow sound only after a
// user gesture: enable() must be called from one (the live view's "Sound on" button).
class AlarmSound {
  constructor() { this.context = null; this.priority = null; this.timer = null; }

  get enabled() { return this.context !== null && this.context.state === "running"; }

  // Switches sound on (from a user gesture) and starts the current priority's burst at once.
  enable() {
    this.context = this.context || new AudioContext();
    return this.context.resume().then(() => {
      clearTimeout(this.timer);
      if (this.priority) this.burst();
    });
  }

  set(priority) {
    if (priority === this.priority) return;
    clearTimeout(this.timer);
    this.priority = priority;
    if (priority) this.burst();
  }

  burst() {
    const schedule = toneSchedule(this.priority);
    if (this.enabled) this.play(schedule);
    this.timer = setTimeout(() => this.burst(), schedule.periodMs);
  }

  play(schedule) {
    const ctx = this.context, start = ctx.currentTime + 0.05;
    const wave = ctx.createPeriodicWave(new Float32Array(HARMONICS + 1),
                                        Float32Array.from([0, ...schedule.harmonicsHz.map((_, n) => 1 / (n + 1))]));
    for (const p of schedule.pulses) {
      const t0 = start + p.startMs / 1000, t1 = t0 + p.lengthMs / 1000, ramp = p.lengthMs / 1000 * 0.15;
      const osc = ctx.createOscillator(), gain = ctx.createGain();
      osc.setPeriodicWave(wave);
      osc.frequency.value = schedule.hz;
      gain.gain.setValueAtTime(0, t0);
      gain.gain.linearRampToValueAtTime(0.3, t0 + ramp);
      gain.gain.setValueAtTime(0.3, t1 - ramp);
      gain.gain.linearRampToValueAtTime(0, t1);
      osc.connect(gain).connect(ctx.destination);
      osc.start(t0);
      osc.stop(t1);
    }
  }
}

//! A training step's clock: its wall time, and the process's CPU time, split into the parts
//! `messages::PHASES` names (what `StepStats::phases` and `phase_cpu` report).

use crate::messages::PHASES;
use crate::render::Deferred;
use std::time::Instant;

/// Splits a step's wall time into `PHASES`, and the process's CPU time with it.
pub(super) struct PhaseClock {
    last: Instant,
    pub(super) spans: Vec<(&'static str, f64)>,
    cpu_last: Option<f64>,
    pub(super) cpu_spans: Vec<(&'static str, f64)>,
}

impl PhaseClock {
    pub(super) fn start() -> Self {
        Self { last: Instant::now(), spans: Vec::new(), cpu_last: crate::threads::process_cpu_seconds(), cpu_spans: Vec::new() }
    }

    /// Ends the current part of the step as the render's three parts, timed by `render`; each
    /// is given the span's CPU time in proportion to its share of the span's wall time, so all
    /// three show the cores the whole span kept busy.
    pub(super) fn mark_render(&mut self, deferred: &Deferred) {
        let cpu = self.cpu_since();
        let now = Instant::now();
        let wall = (now - self.last).as_secs_f64();
        for (k, seconds) in deferred.seconds.iter().enumerate() {
            self.spans.push((PHASES[2 + k], *seconds));
            if let Some(cpu) = cpu {
                self.cpu_spans.push((PHASES[2 + k], if wall > 0.0 { cpu * seconds / wall } else { 0.0 }));
            }
        }
        self.last = now;
    }

    /// Ends the current part of the step as `PHASES[k]`.
    pub(super) fn mark(&mut self, k: usize) {
        let now = Instant::now();
        self.spans.push((PHASES[k], (now - self.last).as_secs_f64()));
        if let Some(cpu) = self.cpu_since() {
            self.cpu_spans.push((PHASES[k], cpu));
        }
        self.last = now;
    }

    /// The process's CPU seconds since the last mark.
    fn cpu_since(&mut self) -> Option<f64> {
        let now = crate::threads::process_cpu_seconds();
        let spent = now.zip(self.cpu_last).map(|(now, last)| now - last);
        self.cpu_last = now;
        spent
    }
}

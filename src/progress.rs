//! Progress of long work on standard error: a bar with an ETA when a person watches a terminal,
//! plain lines (position, percentage, elapsed time, ETA, the latest message) every tenth of
//! the work and at least every ten seconds when nobody does (a log file, CI, `nohup`), where indicatif would print nothing.

use std::io::IsTerminal;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// How often a plain line is printed at most: every this fraction of the work...
const LINE_FRACTION: f64 = 0.1;
/// ...or after this long without one (a silent log longer than this looks hung).
const LINE_INTERVAL: Duration = Duration::from_secs(10);

pub struct Progress {
    bar: Option<indicatif::ProgressBar>,
    plain: Mutex<Plain>,
}

struct Plain {
    what: String,
    message: String,
    length: u64,
    position: u64,
    /// Where the ETA is measured from (reset when the work restarts, e.g. a resumed fit).
    start: Instant,
    start_position: u64,
    last_line: Instant,
    last_line_position: u64,
}

impl Progress {
    /// Progress over `total` units of `what`; a bar when standard error is a terminal.
    pub fn new(total: u64, what: &str) -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = indicatif::ProgressBar::new(total);
            let style = indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta} {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
                .progress_chars("=> ");
            bar.set_style(style);
            bar.set_prefix(what.to_string());
            bar
        });
        let now = Instant::now();
        let plain = Plain {
            what: what.to_string(),
            message: String::new(),
            length: total,
            position: 0,
            start: now,
            start_position: 0,
            last_line: now,
            last_line_position: 0,
        };
        Progress { bar, plain: Mutex::new(plain) }
    }

    fn with_plain(&self, f: impl FnOnce(&mut Plain)) {
        if let Ok(mut plain) = self.plain.lock() {
            f(&mut plain);
        }
    }

    pub fn set_length(&self, length: u64) {
        if let Some(bar) = &self.bar {
            bar.set_length(length);
        }
        self.with_plain(|p| p.length = length);
    }

    pub fn set_position(&self, position: u64) {
        if let Some(bar) = &self.bar {
            bar.set_position(position);
            return;
        }
        self.with_plain(|p| {
            p.position = position;
            let step = ((p.length as f64 * LINE_FRACTION).ceil() as u64).max(1);
            let due =
                position >= p.last_line_position + step || p.last_line.elapsed() >= LINE_INTERVAL || (position == p.length && position != p.last_line_position);
            if due {
                eprintln!("{}", p.line());
                p.last_line = Instant::now();
                p.last_line_position = position;
            }
        });
    }

    /// What the work now is ("evaluating" after "fitting"): the bar's label and the plain
    /// lines' first word.
    pub fn set_what(&self, what: &str) {
        if let Some(bar) = &self.bar {
            bar.set_prefix(what.to_string());
        }
        self.with_plain(|p| p.what = what.to_string());
    }

    pub fn set_message(&self, message: String) {
        match &self.bar {
            Some(bar) => bar.set_message(message),
            None => self.with_plain(|p| p.message = message),
        }
    }

    /// Restarts the ETA's clock from the current position.
    pub fn reset_eta(&self) {
        if let Some(bar) = &self.bar {
            bar.reset_eta();
        }
        self.with_plain(|p| {
            p.start = Instant::now();
            p.start_position = p.position;
            p.last_line_position = p.position;
        });
    }

    /// A line above the bar (or simply a line).
    pub fn println(&self, line: String) {
        match &self.bar {
            Some(bar) => bar.println(line),
            None => eprintln!("{line}"),
        }
    }

    pub fn finish_and_clear(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

impl Plain {
    fn line(&self) -> String {
        let elapsed = self.start.elapsed().as_secs_f64();
        let done = self.position.saturating_sub(self.start_position) as f64;
        let left = self.length.saturating_sub(self.position) as f64;
        let eta = if done > 0.0 { clock(elapsed / done * left) } else { "?".into() };
        let percent = if self.length > 0 { 100.0 * self.position as f64 / self.length as f64 } else { 0.0 };
        let message = if self.message.is_empty() { String::new() } else { format!(" {}", self.message) };
        format!("{}: {}/{} ({percent:.0}%), {} elapsed, eta {eta}{message}", self.what, self.position, self.length, clock(elapsed))
    }
}

/// Seconds as `h:mm:ss` or `m:ss`.
fn clock(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    if s >= 3600 {
        format!("{}:{:02}:{:02}", s / 3600, s / 60 % 60, s % 60)
    } else {
        format!("{}:{:02}", s / 60, s % 60)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plain_lines_give_the_position_and_an_eta() {
        let mut p = Plain {
            what: "fitting".into(),
            message: "loss 0.1".into(),
            length: 100,
            position: 50,
            start: Instant::now() - Duration::from_secs(60),
            start_position: 0,
            last_line: Instant::now(),
            last_line_position: 0,
        };
        let line = p.line();
        assert!(line.starts_with("fitting: 50/100 (50%), 1:00 elapsed, eta 1:00 loss 0.1"), "{line}");
        p.position = 0;
        assert!(p.line().contains("eta ?"));
        assert_eq!(clock(3725.0), "1:02:05");
    }
}

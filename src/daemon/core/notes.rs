//! STATUSTEXT: what the core says to the ground (and to the log), chunked as MAVLink 2
//! allows and bounded, so a burst of notices cannot crowd out the heartbeat.

use std::collections::VecDeque;

use mavlink::dialects::common::{MavMessage, MavSeverity, STATUSTEXT_DATA};

/// Text messages waiting to go out. Beyond `CAP` the oldest are dropped and counted: a
/// flood of notices is worth a counter, not unbounded memory.
#[derive(Debug, Default)]
pub struct Notes {
    queue: VecDeque<MavMessage>,
    next_id: u16,
    pub dropped: u64,
}

const CAP: usize = 64;
/// Characters per STATUSTEXT chunk (the field's size).
const CHUNK: usize = 50;

impl Notes {
    /// Logs `log` as a warning and sends only `short`, which fits one STATUSTEXT.
    pub fn warn_short(&mut self, log: &str, short: &str) {
        tracing::warn!("{log}");
        self.queue_text(MavSeverity::MAV_SEVERITY_WARNING, short);
    }

    /// Queues `text` (prefixed "mavloc: ") and logs it at the matching level.
    pub fn push(&mut self, severity: MavSeverity, text: &str) {
        match severity {
            MavSeverity::MAV_SEVERITY_EMERGENCY
            | MavSeverity::MAV_SEVERITY_ALERT
            | MavSeverity::MAV_SEVERITY_CRITICAL
            | MavSeverity::MAV_SEVERITY_ERROR => tracing::error!("{text}"),
            MavSeverity::MAV_SEVERITY_WARNING => tracing::warn!("{text}"),
            _ => tracing::info!("{text}"),
        }
        self.queue_text(severity, text);
    }

    /// The STATUSTEXT chunks of `text`, queued.
    fn queue_text(&mut self, severity: MavSeverity, text: &str) {
        let line = format!("mavloc: {text}");
        let chunks: Vec<&[u8]> = line.as_bytes().chunks(CHUNK).collect();
        // A multi-chunk text shares a non-zero id so the receiver can reassemble it.
        let id = if chunks.len() > 1 {
            self.next_id = self.next_id.wrapping_add(1).max(1);
            self.next_id
        } else {
            0
        };
        for (i, c) in chunks.iter().enumerate() {
            let mut text = [0u8; CHUNK];
            text[..c.len()].copy_from_slice(c);
            if self.queue.len() >= CAP {
                self.queue.pop_front();
                self.dropped += 1;
            }
            self.queue.push_back(MavMessage::STATUSTEXT(STATUSTEXT_DATA {
                severity,
                text: text.into(),
                id,
                chunk_seq: i as u8,
            }));
        }
    }

    pub fn info(&mut self, text: &str) {
        self.push(MavSeverity::MAV_SEVERITY_INFO, text)
    }

    pub fn warn(&mut self, text: &str) {
        self.push(MavSeverity::MAV_SEVERITY_WARNING, text)
    }

    pub fn error(&mut self, text: &str) {
        self.push(MavSeverity::MAV_SEVERITY_ERROR, text)
    }

    pub fn pop(&mut self) -> Option<MavMessage> {
        self.queue.pop_front()
    }

    pub fn len(&self) -> usize {
        self.queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }
}

/// Per-sender allowance for things done on a peer's behalf that cost the disk or the link
/// (a log line or STATUSTEXT about a refused set, a DENIED answer to a stranger's
/// command): at most `per_sender` in a period from each sender, and `all` from all
/// senders together; the rest are only counted. A flood costs a counter. Senders are
/// bounded too (the oldest is forgotten), which is why the total is capped: a flood
/// cycling through more senders than are remembered (the audit's 65 component ids) would
/// find each one forgotten and be answered in full.
#[derive(Debug)]
pub struct SenderLimit {
    period: std::time::Duration,
    per_sender: u32,
    all: u32,
    /// Each sender's current period: its start and the count allowed in it.
    last: std::collections::BTreeMap<(u8, u8), (super::time::Mono, u32)>,
    /// The same for all senders together.
    window: Option<(super::time::Mono, u32)>,
    pub suppressed: u64,
}

impl Default for SenderLimit {
    /// Lines about a peer: one per sender per 10 s, 16 of all senders.
    fn default() -> SenderLimit {
        SenderLimit::new(std::time::Duration::from_secs(10), 1, 16)
    }
}

impl SenderLimit {
    const SENDERS: usize = 64;

    pub fn new(period: std::time::Duration, per_sender: u32, all: u32) -> SenderLimit {
        SenderLimit { period, per_sender, all, last: Default::default(), window: None, suppressed: 0 }
    }

    /// Whether something on behalf of `from` may be done at `now`.
    pub fn allow(&mut self, from: (u8, u8), now: super::time::Mono) -> bool {
        let current = |w: Option<(super::time::Mono, u32)>| match w {
            Some((start, n)) if now.saturating_sub(start) < self.period => (start, n),
            _ => (now, 0),
        };
        let window = current(self.window);
        let sender = current(self.last.get(&from).copied());
        if sender.1 >= self.per_sender || window.1 >= self.all {
            self.suppressed += 1;
            return false;
        }
        if self.last.len() >= Self::SENDERS && !self.last.contains_key(&from) {
            let oldest = self.last.iter().min_by_key(|(_, (t, _))| *t).map(|(k, _)| *k);
            if let Some(k) = oldest {
                self.last.remove(&k);
            }
        }
        self.last.insert(from, (sender.0, sender.1 + 1));
        self.window = Some((window.0, window.1 + 1));
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunks(n: &mut Notes) -> Vec<(u16, u8)> {
        std::iter::from_fn(|| n.pop())
            .map(|m| match m {
                MavMessage::STATUSTEXT(s) => (s.id, s.chunk_seq),
                other => panic!("{other:?}"),
            })
            .collect()
    }

    #[test]
    fn long_texts_are_chunked_under_one_nonzero_id() {
        let mut n = Notes::default();
        n.info(&"x".repeat(120));
        let c = chunks(&mut n);
        assert_eq!(c.iter().map(|c| c.1).collect::<Vec<_>>(), vec![0, 1, 2]);
        assert!(c.iter().all(|(id, _)| *id == c[0].0 && *id != 0));
        n.info("short");
        assert_eq!(chunks(&mut n), vec![(0, 0)], "one chunk: id 0");
    }

    /// One line per sender per period, and at most `ALL_SENDERS` of all senders: a flood
    /// cycling through more senders than are remembered (the audit's 65 component ids
    /// wrote 10,000 lines for 10,000 refusals) is said a bounded number of times.
    #[test]
    fn refusals_from_many_senders_are_bounded_together() {
        use super::super::time::Mono;
        use std::time::Duration;
        let mut l = SenderLimit::default();
        let mut said = 0;
        for i in 0..10_000u32 {
            let now = Mono::ZERO + Duration::from_millis(u64::from(i)); // 10 s in all
            said += usize::from(l.allow((255, (i % 65) as u8), now));
        }
        assert_eq!(said, 16, "one period's worth");
        assert_eq!(l.suppressed, 10_000 - said as u64);
        // The next period says again, and a sender already said this period stays quiet.
        let later = Mono::ZERO + Duration::from_secs(11);
        assert!(l.allow((1, 1), later));
        assert!(!l.allow((1, 1), later + Duration::from_secs(1)));
        assert!(l.allow((1, 1), later + Duration::from_secs(11)));
    }

    #[test]
    fn a_flood_is_bounded_and_counted() {
        let mut n = Notes::default();
        for i in 0..1000 {
            n.warn(&format!("notice {i}"));
        }
        assert_eq!(n.len(), CAP);
        assert_eq!(n.dropped, 1000 - CAP as u64);
        // The newest survive.
        let MavMessage::STATUSTEXT(last) = std::iter::from_fn(|| n.pop()).last().unwrap() else { panic!() };
        assert!(String::from_utf8_lossy(&last.text[..]).contains("notice 999"));
    }
}

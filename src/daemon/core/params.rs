//! The parameter server's output side: PARAM_VALUEs are produced lazily and paced, never
//! queued by the hundred. A PARAM_REQUEST_LIST starts (or restarts) a cursor over the
//! table; single answers (READ, SET) jump ahead from a small deduplicated set. Pacing
//! keeps a whole list within what PX4 forwards to a ground station behind it: a burst
//! of 40 values lost most of them there.

use std::collections::BTreeSet;
use std::time::Duration;

use super::time::Mono;

/// At least this long between two PARAM_VALUEs: at most 5 in any 50 ms.
pub const PARAM_INTERVAL: Duration = Duration::from_millis(10);

#[derive(Debug)]
pub struct ParamPacer {
    count: usize,
    cursor: Option<usize>,
    jump: BTreeSet<usize>,
    next: Mono,
}

impl ParamPacer {
    pub fn new(count: usize) -> ParamPacer {
        ParamPacer { count, cursor: None, jump: BTreeSet::new(), next: Mono::ZERO }
    }

    /// PARAM_REQUEST_LIST: the whole table, from index 0 (a second list restarts it).
    pub fn on_list(&mut self) {
        self.cursor = Some(0);
    }

    /// One value owed (READ, SET answer, REQUEST_MESSAGE).
    pub fn on_single(&mut self, index: usize) {
        if index < self.count {
            self.jump.insert(index);
        }
    }

    /// Values owed but not sent yet.
    pub fn queued(&self) -> usize {
        self.jump.len() + self.cursor.map_or(0, |c| self.count - c)
    }

    fn busy(&self) -> bool {
        self.cursor.is_some() || !self.jump.is_empty()
    }

    /// The index of the next PARAM_VALUE to send, if pacing allows it now.
    pub fn poll(&mut self, now: Mono) -> Option<usize> {
        if !self.busy() || now < self.next {
            return None;
        }
        let i = match self.jump.pop_first() {
            Some(i) => i,
            None => {
                let c = self.cursor.expect("busy");
                self.cursor = (c + 1 < self.count).then_some(c + 1);
                c
            }
        };
        self.next = now + PARAM_INTERVAL;
        Some(i)
    }

    /// While values are owed and pacing holds them back: the next allowed send.
    pub fn deadline(&self) -> Option<Mono> {
        self.busy().then_some(self.next)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Drives the pacer like the shell does: send whatever is allowed, then sleep until
    /// its deadline. Returns the send times by index.
    fn drain(p: &mut ParamPacer, mut now: Mono) -> Vec<(Mono, usize)> {
        let mut out = Vec::new();
        for _ in 0..10_000 {
            while let Some(i) = p.poll(now) {
                out.push((now, i));
            }
            match p.deadline() {
                Some(d) => now = d.max(now),
                None => break,
            }
        }
        out
    }

    #[test]
    fn a_list_sends_every_index_once_paced() {
        let mut p = ParamPacer::new(40);
        p.on_list();
        let sent = drain(&mut p, Mono::ZERO);
        assert_eq!(sent.iter().map(|s| s.1).collect::<Vec<_>>(), (0..40).collect::<Vec<_>>());
        for w in sent.windows(2) {
            assert!(w[1].0.saturating_sub(w[0].0) >= PARAM_INTERVAL);
        }
        assert_eq!(p.queued(), 0);
    }

    #[test]
    fn reads_jump_ahead_and_duplicates_collapse() {
        let mut p = ParamPacer::new(40);
        p.on_list();
        assert_eq!(p.poll(Mono::ZERO), Some(0));
        for _ in 0..500 {
            p.on_single(30);
        }
        p.on_single(99); // out of range: ignored
        assert_eq!(p.queued(), 39 + 1);
        let sent = drain(&mut p, Mono::ZERO);
        assert_eq!(sent[0].1, 30, "the read answer jumps the queue");
        assert_eq!(sent.len(), 40);
    }

    proptest! {
        #[test]
        fn never_more_than_five_in_any_50_ms(ops in proptest::collection::vec((0u64..200, 0usize..45, any::<bool>()), 1..60)) {
            let mut p = ParamPacer::new(40);
            let mut now = Mono::ZERO;
            let mut sent: Vec<Mono> = Vec::new();
            for (dt, idx, list) in ops {
                now = now + Duration::from_millis(dt);
                if list { p.on_list() } else { p.on_single(idx) }
                while p.poll(now).is_some() { sent.push(now); }
                if let Some(d) = p.deadline() { prop_assert!(d > now || p.poll(now).is_none()); }
            }
            sent.extend(drain(&mut p, now).into_iter().map(|s| s.0));
            for (i, t) in sent.iter().enumerate() {
                let within = sent[i..].iter().take_while(|u| u.0 < t.0 + 50_000).count();
                prop_assert!(within <= 5, "{within} values within 50 ms of {t:?}");
            }
        }
    }
}

//! The autopilot's EVENT messages (MAVLink events protocol). PX4 says why it refuses to
//! arm or to switch mode only as EVENTs with a COMMAND_ACK, never as STATUSTEXT
//! (measured: `../shared/data/px4-sitl/px4_sih_prearm_events.txt`). An EVENT carries an id
//! and packed arguments; its words are in the autopilot's event metadata (PX4's build
//! writes `events/all_events.json`), which the shell loads from `mavlink.px4_events`.
//! Without it a few ids mavloc's start-up depends on are known by heart; the rest are
//! shown by number.

use std::collections::{BTreeMap, VecDeque};

use mavlink::dialects::common::EVENT_DATA;
use serde_json::Value;

use super::time::Mono;

/// MAV_SEVERITY numbering of the events' external log level.
pub const WARNING: u8 = 4;
/// Events kept for status.
const KEPT: usize = 8;

/// PX4 v1.16 events the GPS-denied start-up meets (id = component << 24 | sub id), from
/// its event metadata; shown even without the metadata file.
const KNOWN: &[(u32, &str)] = &[
    (0x0102_089d, "Arming denied: Resolve system health failures first"),
    (0x0193_fa1b, "Horizontal position unstable"),
    (0x01d3_1bb9, "Navigation error: No valid position estimate"),
    (0x0198_c273, "Navigation error: No valid global position estimate"),
    (0x01a8_93e0, "Arming check summary event"),
];

#[derive(Clone, Debug)]
struct Def {
    message: String,
    /// Argument types as the metadata names them.
    args: Vec<String>,
}

#[derive(Clone, Debug)]
struct Enum {
    bits: bool,
    base: String,
    entries: BTreeMap<u64, String>,
}

/// Event definitions from an `all_events.json`.
#[derive(Clone, Debug, Default)]
pub struct EventMetadata {
    defs: BTreeMap<u32, Def>,
    enums: BTreeMap<String, Enum>,
}

impl EventMetadata {
    /// Parses PX4's `all_events.json` (components -> event_groups -> events, and enums).
    pub fn parse(json: &str) -> Result<EventMetadata, String> {
        let v: Value = serde_json::from_str(json).map_err(|e| format!("not JSON: {e}"))?;
        let comps =
            v["components"].as_object().ok_or("no \"components\" object: not an events metadata file")?;
        let mut m = EventMetadata::default();
        for (cid, comp) in comps {
            let cid: u32 = cid.parse().map_err(|_| format!("component id {cid:?} is not a number"))?;
            for (name, e) in comp["enums"].as_object().into_iter().flatten() {
                let entries = e["entries"]
                    .as_object()
                    .into_iter()
                    .flatten()
                    .filter_map(|(k, v)| Some((k.parse().ok()?, v["description"].as_str()?.to_string())))
                    .collect();
                m.enums.insert(
                    name.clone(),
                    Enum {
                        bits: e["is_bitfield"].as_bool().unwrap_or(false),
                        base: e["type"].as_str().unwrap_or("uint8_t").to_string(),
                        entries,
                    },
                );
            }
            for group in comp["event_groups"].as_object().into_iter().flatten().map(|(_, g)| g) {
                for (sub, e) in group["events"].as_object().into_iter().flatten() {
                    let Ok(sub) = sub.parse::<u32>() else { continue };
                    let args = e["arguments"]
                        .as_array()
                        .into_iter()
                        .flatten()
                        .map(|a| a["type"].as_str().unwrap_or("").to_string())
                        .collect();
                    let message = e["message"].as_str().unwrap_or("").to_string();
                    m.defs.insert(cid << 24 | (sub & 0xff_ffff), Def { message, args });
                }
            }
        }
        if m.defs.is_empty() {
            return Err("no events defined".into());
        }
        Ok(m)
    }

    pub fn len(&self) -> usize {
        self.defs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.defs.is_empty()
    }

    /// The event in words: the message with its arguments filled in.
    pub fn describe(&self, id: u32, args: &[u8]) -> Option<String> {
        let def = self.defs.get(&id)?;
        let mut values = Vec::new();
        let mut at = 0;
        for ty in &def.args {
            let (text, size) = self.value(ty, &args[at.min(args.len())..])?;
            values.push(text);
            at += size;
        }
        let mut line = fill(&def.message, &values);
        // A summary's words are its arguments.
        if def.message.ends_with("summary event") && !values.is_empty() {
            line = format!("{line}: {}", values.join(", "));
        }
        Some(strip_tags(&line))
    }

    fn value(&self, ty: &str, bytes: &[u8]) -> Option<(String, usize)> {
        let name = ty.rsplit("::").next().unwrap_or(ty);
        if let Some(e) = self.enums.get(name) {
            let (raw, size) = number(&e.base, bytes)?;
            let raw = raw as u64;
            let text = if e.bits {
                let names: Vec<&str> = e
                    .entries
                    .iter()
                    .filter(|(b, _)| **b != 0 && raw & **b == **b)
                    .map(|(_, n)| n.as_str())
                    .collect();
                if names.is_empty() {
                    "none".into()
                } else {
                    names.join("|")
                }
            } else {
                e.entries.get(&raw).cloned().unwrap_or_else(|| raw.to_string())
            };
            return Some((text, size));
        }
        let (v, size) = number(name, bytes)?;
        let text = if name == "float" { format!("{v:.2}") } else { format!("{v}") };
        Some((text, size))
    }
}

/// A little-endian number of a C type at the start of `b` (missing bytes read as zero,
/// as the protocol pads arguments to 40 bytes).
fn number(ty: &str, b: &[u8]) -> Option<(f64, usize)> {
    let size = match ty {
        "uint8_t" | "int8_t" | "bool" => 1,
        "uint16_t" | "int16_t" => 2,
        "uint32_t" | "int32_t" | "float" => 4,
        "uint64_t" | "int64_t" => 8,
        _ => return None,
    };
    let mut raw = [0u8; 8];
    let n = size.min(b.len());
    raw[..n].copy_from_slice(&b[..n]);
    let v = match ty {
        "uint8_t" | "bool" => raw[0] as f64,
        "int8_t" => raw[0] as i8 as f64,
        "uint16_t" => u16::from_le_bytes([raw[0], raw[1]]) as f64,
        "int16_t" => i16::from_le_bytes([raw[0], raw[1]]) as f64,
        "uint32_t" => u32::from_le_bytes(raw[..4].try_into().ok()?) as f64,
        "int32_t" => i32::from_le_bytes(raw[..4].try_into().ok()?) as f64,
        "float" => f32::from_le_bytes(raw[..4].try_into().ok()?) as f64,
        "uint64_t" => u64::from_le_bytes(raw) as f64,
        _ => i64::from_le_bytes(raw) as f64,
    };
    Some((v, size))
}

/// `{1}`, `{2:.1}`, ... replaced by the arguments (1-based).
fn fill(template: &str, values: &[String]) -> String {
    let mut out = String::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let Some(close) = rest[open..].find('}') else { break };
        let inner = &rest[open + 1..open + close];
        let index = inner.split(':').next().and_then(|n| n.parse::<usize>().ok());
        match index.and_then(|i| values.get(i.wrapping_sub(1))) {
            Some(v) => out.push_str(v),
            None => out.push_str(&rest[open..=open + close]),
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

/// `<param>EKF2_GPS_CTRL</param>` and the like: keep the words.
fn strip_tags(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut in_tag = false;
    for c in s.chars() {
        match c {
            '<' => in_tag = true,
            '>' if in_tag => in_tag = false,
            c if !in_tag => out.push(c),
            _ => {}
        }
    }
    out
}

/// One event as received.
#[derive(Clone, Debug, PartialEq)]
pub struct Seen {
    pub at: Mono,
    pub id: u32,
    /// MAV_SEVERITY numbering (0 emergency .. 7 debug).
    pub level: u8,
    pub text: String,
}

/// The newest events, and their words.
#[derive(Debug, Default)]
pub struct EventLog {
    metadata: Option<EventMetadata>,
    seen: VecDeque<Seen>,
    last_sequence: Option<u16>,
}

impl EventLog {
    pub fn set_metadata(&mut self, m: EventMetadata) {
        self.metadata = Some(m);
    }

    pub fn recent(&self) -> impl Iterator<Item = &Seen> {
        self.seen.iter()
    }

    /// The event's level and the line to log; None for a repeat (the autopilot resends
    /// an event until it is acknowledged or its sequence moves on).
    pub fn on_event(&mut self, at: Mono, e: &EVENT_DATA) -> Option<(u8, String)> {
        if self.last_sequence == Some(e.sequence) {
            return None;
        }
        self.last_sequence = Some(e.sequence);
        let level = e.log_levels & 0x0f;
        let words = self
            .metadata
            .as_ref()
            .and_then(|m| m.describe(e.id, &e.arguments))
            .or_else(|| KNOWN.iter().find(|(id, _)| *id == e.id).map(|(_, t)| t.to_string()))
            .unwrap_or_else(|| "(no event metadata for this id: mavlink.px4_events)".into());
        let text = format!("autopilot event {:#010x}: {words}", e.id);
        if self.seen.len() >= KEPT {
            self.seen.pop_front();
        }
        self.seen.push_back(Seen { at, id: e.id, level, text: text.clone() });
        Some((level, text))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const META: &str = r#"{"components": {"1": {"namespace": "px4",
        "enums": {"health_component_t": {"type": "uint32_t", "is_bitfield": true, "entries": {
            "1": {"name": "none", "description": "None"},
            "1048576": {"name": "system", "description": "System"},
            "131072": {"name": "local_position_estimate", "description": "Local position estimate"}}}},
        "event_groups": {"default": {"events": {
            "133277": {"name": "commander_arm_denied_resolve_failures", "message": "Arming denied: Resolve system health failures first"},
            "999": {"name": "x", "message": "Battery at {1:.1} V, <param>BAT_LOW</param> is {2}", "arguments": [{"name": "v", "type": "float"}, {"name": "p", "type": "uint8_t"}]}}},
        "arming_check": {"events": {
            "11047904": {"name": "commander_arming_check_summary", "message": "Arming check summary event",
                "arguments": [{"name": "chunk_idx", "type": "uint8_t"}, {"name": "error", "type": "px4::health_component_t"}]}}}}}}}"#;

    fn event(id: u32, seq: u16, args: &[u8]) -> EVENT_DATA {
        let mut a = [0u8; 40];
        a[..args.len()].copy_from_slice(args);
        EVENT_DATA { id, sequence: seq, log_levels: 0x62, arguments: a, ..Default::default() }
    }

    #[test]
    fn px4_refusals_are_put_in_words_from_the_metadata() {
        let m = EventMetadata::parse(META).unwrap();
        let mut log = EventLog::default();
        log.set_metadata(m);
        let (level, line) = log.on_event(Mono::ZERO, &event(0x0102_089d, 1, &[])).unwrap();
        assert_eq!(level, 2, "external level: the low nibble");
        assert!(line.ends_with("Arming denied: Resolve system health failures first"), "{line}");
        assert_eq!(log.on_event(Mono::ZERO, &event(0x0102_089d, 1, &[])), None, "a resend is not news");
        let mut args = vec![0u8];
        args.extend((1_048_576u32 | 131_072).to_le_bytes());
        let (_, line) = log.on_event(Mono::ZERO, &event(0x01a8_93e0, 2, &args)).unwrap();
        assert!(line.contains("Local position estimate|System"), "{line}");
        let mut args = 11.55f32.to_le_bytes().to_vec();
        args.push(3);
        let (_, line) = log.on_event(Mono::ZERO, &event(999 | 1 << 24, 3, &args)).unwrap();
        assert!(line.ends_with("Battery at 11.55 V, BAT_LOW is 3"), "{line}");
    }

    #[test]
    fn without_metadata_the_start_up_refusals_are_still_known() {
        let mut log = EventLog::default();
        let (_, line) = log.on_event(Mono::ZERO, &event(0x0102_089d, 7, &[])).unwrap();
        assert!(line.contains("Arming denied"), "{line}");
        let (_, line) = log.on_event(Mono::ZERO, &event(0x0100_0001, 8, &[])).unwrap();
        assert!(line.contains("no event metadata"), "{line}");
        assert_eq!(log.recent().count(), 2);
    }

    #[test]
    fn a_file_that_is_not_event_metadata_is_refused_with_the_reason() {
        assert!(EventMetadata::parse("{}").unwrap_err().contains("components"));
        assert!(EventMetadata::parse("nope").unwrap_err().contains("not JSON"));
    }
}

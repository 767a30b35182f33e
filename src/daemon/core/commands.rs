//! Commands addressed to mavloc (COMMAND_LONG), decided without I/O: every command gets
//! exactly one final COMMAND_ACK. Work the shell must do first (write a snapshot, start
//! a pipeline) is acknowledged IN_PROGRESS and owed a final ACK under a token until the
//! shell reports it done, as quinn-proto owes an answer to every `Incoming`.
//!
//! Command ids (documented in the README):
//! * `MAV_CMD_USER_1` (31010), pipeline control: param1 = pipeline (0 the configured one,
//!   1 area, 2 indoor), param2 = action (0 stop, 1 start, 2 reset, 3 adjust the area map
//!   now, as at a touchdown: `daemon::flightlog`).
//! * `MAV_CMD_USER_2` (31011), result snapshot: writes the current results to the state
//!   directory; acknowledged `IN_PROGRESS`, then `ACCEPTED` or `FAILED`.
//! * `MAV_CMD_REQUEST_MESSAGE` (512) for HEARTBEAT (0), PARAM_VALUE (22, param2 = index)
//!   and COMPONENT_METADATA (397: where the parameter metadata is, over MAVLink FTP).

use std::collections::BTreeMap;

use mavlink::dialects::common::*;

use crate::settings::PipelineKind;

pub const CMD_PIPELINE: u32 = 31010;
pub const CMD_SNAPSHOT: u32 = 31011;

/// What an inbound command asks for, once judged.
#[derive(Clone, Debug, PartialEq)]
pub enum Decision {
    /// Answer now with this result.
    Ack(MavResult),
    /// Not ours (a broadcast for some other component): say nothing.
    Ignore,
    Pipeline(PipelineRequest),
    Snapshot,
    SendHeartbeat,
    SendParam(usize),
    SendMetadata,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PipelineRequest {
    Start(PipelineKind),
    Stop,
    Reset,
    AdjustMap,
}

/// Judges a command addressed to mavloc (trust is checked by the caller). `configured`
/// is the pipeline `LOC_PIPELINE` selects; `params` the number of parameters.
pub fn decide(c: &COMMAND_LONG_DATA, broadcast: bool, configured: PipelineKind, params: usize) -> Decision {
    let id = c.command as u32;
    let ours = matches!(id, CMD_PIPELINE | CMD_SNAPSHOT) || c.command == MavCmd::MAV_CMD_REQUEST_MESSAGE;
    if broadcast && !ours {
        return Decision::Ignore; // other components will answer
    }
    let denied = Decision::Ack(MavResult::MAV_RESULT_DENIED);
    match id {
        CMD_PIPELINE => {
            // NaN and fractions are refused, never read as 0 ("stop").
            let whole = |x: f32| (x.is_finite() && x.fract() == 0.0).then_some(x as i32);
            let kind = match whole(c.param1) {
                Some(0) => configured,
                Some(1) => PipelineKind::Area,
                Some(2) => PipelineKind::Indoor,
                _ => return denied,
            };
            match whole(c.param2) {
                Some(0) => Decision::Pipeline(PipelineRequest::Stop),
                Some(1) => Decision::Pipeline(PipelineRequest::Start(kind)),
                Some(2) => Decision::Pipeline(PipelineRequest::Reset),
                Some(3) => Decision::Pipeline(PipelineRequest::AdjustMap),
                _ => denied,
            }
        }
        CMD_SNAPSHOT => Decision::Snapshot,
        _ if c.command == MavCmd::MAV_CMD_REQUEST_MESSAGE => {
            let index = c.param2;
            if c.param1 == 0.0 {
                Decision::SendHeartbeat
            } else if c.param1 == 397.0 {
                Decision::SendMetadata
            } else if c.param1 == 22.0 && index >= 0.0 && index.fract() == 0.0 && (index as usize) < params {
                Decision::SendParam(index as usize)
            } else {
                Decision::Ack(MavResult::MAV_RESULT_UNSUPPORTED)
            }
        }
        _ => Decision::Ack(MavResult::MAV_RESULT_UNSUPPORTED),
    }
}

/// Final ACKs owed: token -> (command, requester, how many asked).
#[derive(Debug, Default)]
pub struct Owed {
    next_token: u64,
    owed: BTreeMap<u64, (MavCmd, (u8, u8), u32)>,
}

impl Owed {
    /// Owes a final ACK. A repeat of a command still being worked on (same command,
    /// same sender: a retransmission) joins it rather than starting the work again;
    /// returns the token only for new work.
    pub fn owe(&mut self, command: MavCmd, to: (u8, u8)) -> Option<u64> {
        if let Some((_, _, n)) = self.owed.values_mut().find(|(c, t, _)| *c == command && *t == to) {
            *n += 1;
            return None;
        }
        self.next_token += 1;
        self.owed.insert(self.next_token, (command, to, 1));
        Some(self.next_token)
    }

    /// The command, its sender and how many final ACKs it is owed.
    pub fn settle(&mut self, token: u64) -> Option<(MavCmd, (u8, u8), u32)> {
        self.owed.remove(&token)
    }

    /// Final ACKs owed in all.
    pub fn len(&self) -> usize {
        self.owed.values().map(|o| o.2 as usize).sum()
    }

    pub fn is_empty(&self) -> bool {
        self.owed.is_empty()
    }
}

pub fn ack(command: MavCmd, result: MavResult, to: (u8, u8)) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        progress: 0,
        result_param2: 0,
        target_system: to.0,
        target_component: to.1,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cmd(command: MavCmd, p1: f32, p2: f32) -> COMMAND_LONG_DATA {
        COMMAND_LONG_DATA { command, param1: p1, param2: p2, ..Default::default() }
    }

    #[test]
    fn pipeline_control_reads_only_whole_finite_values() {
        let d = |p1, p2| decide(&cmd(MavCmd::MAV_CMD_USER_1, p1, p2), false, PipelineKind::Area, 40);
        assert_eq!(d(1.0, 1.0), Decision::Pipeline(PipelineRequest::Start(PipelineKind::Area)));
        assert_eq!(d(0.0, 0.0), Decision::Pipeline(PipelineRequest::Stop));
        assert_eq!(d(2.0, 2.0), Decision::Pipeline(PipelineRequest::Reset));
        assert_eq!(d(1.0, 3.0), Decision::Pipeline(PipelineRequest::AdjustMap));
        for (p1, p2) in
            [(1.0, f32::NAN), (f32::NAN, 1.0), (1.0, 0.5), (7.0, 1.0), (1.0, f32::INFINITY), (1.0, 4.0)]
        {
            assert_eq!(d(p1, p2), Decision::Ack(MavResult::MAV_RESULT_DENIED), "({p1}, {p2})");
        }
    }

    #[test]
    fn broadcasts_of_others_commands_are_left_alone_unknown_ones_unsupported() {
        let set_mode = cmd(MavCmd::MAV_CMD_DO_SET_MODE, 0.0, 0.0);
        assert_eq!(decide(&set_mode, true, PipelineKind::Area, 40), Decision::Ignore);
        assert_eq!(
            decide(&set_mode, false, PipelineKind::Area, 40),
            Decision::Ack(MavResult::MAV_RESULT_UNSUPPORTED)
        );
        let req =
            |p1, p2| decide(&cmd(MavCmd::MAV_CMD_REQUEST_MESSAGE, p1, p2), false, PipelineKind::Area, 40);
        assert_eq!(req(0.0, 0.0), Decision::SendHeartbeat);
        assert_eq!(req(22.0, 3.0), Decision::SendParam(3));
        assert_eq!(req(22.0, 40.0), Decision::Ack(MavResult::MAV_RESULT_UNSUPPORTED));
        assert_eq!(req(22.0, f32::NAN), Decision::Ack(MavResult::MAV_RESULT_UNSUPPORTED));
    }
}

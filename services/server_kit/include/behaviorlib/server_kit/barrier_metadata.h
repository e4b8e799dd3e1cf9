#pragma once

// Call metadata of the deterministic mode's barrier, shared by the
// simulator and the behavior systems that follow its time grants.

namespace behaviorlib::server_kit {

/// Names a StreamSetpoints call's key in the follower's SetpointLedger: its
/// time reports count the setpoints written on it
/// (FollowTimeRequest.setpoints_written), and the simulator applies them
/// before it steps on.
inline constexpr char kSetpointStreamMetadataKey[] = "behaviorlib-setpoint-stream";

}  // namespace behaviorlib::server_kit

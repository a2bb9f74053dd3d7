//! hil-mocks' device tests, one binary: each mock against our driver (and against outside peers)
//! over the transport it has on the robot. One binary, not five, so that the two 30 s streams run
//! side by side and the test build links once (CI on 2 cores: README).

mod lpms_pty;
mod lpms_session_sim;
mod teco_drives;
mod teco_socketcand;
mod tim551_loopback;

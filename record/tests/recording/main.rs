//! amr-record's tests, one binary (three before, so that the test build links once): the live view
//! on loopback, record and replay of the real server actor tree, and the ROS 2 encoding read back
//! by independent readers.

mod live;
mod record_replay;
mod ros2_bag;

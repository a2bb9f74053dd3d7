//! ROS 2 without a ROS installation: what the fleet needs to write ROS 2 bags and to be a ROS 2
//! node on the wire.
//!
//! - [`cdr`]: the CDR encoding of ROS 2 messages (one implementation for writing and reading);
//! - [`msg`]: the message types the fleet speaks, their schema text and their REP 2011 type hashes;
//! - [`rmw_zenoh`]: rmw_zenoh's key expressions, liveliness tokens, QoS strings, GIDs and sample
//!   attachments;
//! - [`node`]: a ROS 2 node on rmw_zenoh (a Zenoh session, its tokens, publishers and subscriptions);
//! - [`dds`]: a ROS 2 node on DDS/RTPS (RustDDS), for Humble's and Foxy's default middleware;
//! - [`transport`]: either node behind one type.
//!
//! Nothing here knows the fleet: the recorder (`amr-record`) turns the fleet's events into these
//! messages.

pub mod cdr;
pub mod dds;
pub mod msg;
pub mod node;
pub mod rmw_zenoh;
pub mod transport;

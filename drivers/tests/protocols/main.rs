//! amr-drivers' protocol tests, one binary (eight before, so that the test build links once): the
//! CANopen master, LPBUS and SOPAS sessions sans-IO, their parsers under property tests, and the
//! captured telegrams and test vectors in `tests/data/`.

mod canopen_master;
mod canopen_proptest;
mod lpms_proptest;
mod lpms_shell;
mod lpms_vectors;
mod sopas_proptest;
mod sopas_samples;
mod sopas_session;

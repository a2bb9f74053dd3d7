//! Supervision: placeholder, being written.

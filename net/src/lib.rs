//! The fleet over the network: Zenoh bridges that hand out the same robot and server link ends as the in-process link (issue 11).

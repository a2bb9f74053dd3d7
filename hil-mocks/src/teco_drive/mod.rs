//! Mock TECO drives: CiA 402 nodes on any CAN transport, and a socketcand server in front of the in-process bus, with a fault plan.

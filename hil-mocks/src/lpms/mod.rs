//! Mock LPMS-B2 behind a pseudo-terminal: the LPBUS command set, streaming from a motion source, with a fault plan.

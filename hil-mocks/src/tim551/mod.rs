//! Mock SICK TiM551: a SOPAS TCP server (both dialects) streaming scans from a scan source, with a fault plan.

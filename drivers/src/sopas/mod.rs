//! SICK TiM551 / TiM5xx over SOPAS (CoLa-A and CoLa-B): codec, scan decoder, session, tokio shell.

//! LP-Research LPMS-B2 over LPBUS: codec, session, tokio-serial shell.

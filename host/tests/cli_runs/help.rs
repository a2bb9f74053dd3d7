//! `amr --help` and every subcommand's `--help`: each subcommand is listed with its own
//! description, and the texts describe the program as it is.
#![allow(clippy::unwrap_used, clippy::expect_used, reason = "test code: a failed step fails the test")]

use std::process::Command;

/// `amr ARGS`' standard output; the command must succeed.
fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_amr")).args(args).env_remove("RUST_LOG").output().unwrap();
    assert!(out.status.success(), "amr {args:?}: {}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

/// The `Commands:` section of a help text: (name, description) per subcommand, without clap's own
/// `help`. A line indented deeper than the names continues the description above it.
fn commands(text: &str) -> Vec<(String, String)> {
    let mut list: Vec<(String, String)> = Vec::new();
    let mut lines = text.lines().skip_while(|l| l.trim_end() != "Commands:").skip(1);
    for line in lines.by_ref() {
        if line.trim().is_empty() {
            break;
        }
        let rest = line.strip_prefix("  ").expect("a command line is indented");
        if rest.starts_with(' ') {
            let (_, description) = list.last_mut().expect("a continuation follows a command");
            description.push(' ');
            description.push_str(rest.trim());
        } else {
            let (name, description) = rest.split_once(' ').unwrap_or((rest, ""));
            list.push((name.to_owned(), description.trim().to_owned()));
        }
    }
    list.retain(|(name, _)| name != "help");
    list
}

/// A description's first sentence: enough of it to recognise it inside another.
fn first_sentence(description: &str) -> &str {
    description.split(". ").next().unwrap_or(description).trim_end_matches('.')
}

#[test]
fn every_subcommand_is_listed_with_its_own_description() {
    let top = commands(&help(&["--help"]));
    let names: Vec<&str> = top.iter().map(|(n, _)| n.as_str()).collect();
    for expected in [
        "config", "localize", "bench", "eval", "sim", "replay", "robot", "server", "estop", "fleet", "mock",
        "tools",
    ] {
        assert!(names.contains(&expected), "`{expected}` missing from amr --help: {names:?}");
    }
    for (name, description) in &top {
        assert!(!description.is_empty(), "`{name}` has no description in amr --help");
        // The subcommand's own help opens with the line's text.
        let own = help(&[name, "--help"]);
        assert!(
            own.starts_with(description.as_str()),
            "`amr {name} --help` does not open with {description:?}"
        );
    }
    for (i, (a, da)) in top.iter().enumerate() {
        for (b, db) in &top[i + 1..] {
            assert_ne!(da, db, "`{a}` and `{b}` share a description");
            assert!(!da.contains(first_sentence(db)), "`{a}`'s line holds `{b}`'s description: {da}");
            assert!(!db.contains(first_sentence(da)), "`{b}`'s line holds `{a}`'s description: {db}");
        }
    }
    let sim = &top.iter().find(|(n, _)| n == "sim").unwrap().1;
    let mock = &top.iter().find(|(n, _)| n == "mock").unwrap().1;
    assert!(mock.contains("mock device"), "{mock}");
    assert!(!sim.contains("mock device standalone"), "{sim}");
}

#[test]
fn the_network_commands_describe_the_link_as_it_is() {
    let robot = help(&["robot", "--help"]);
    assert!(!robot.contains("user/password"), "{robot}");
    assert!(robot.contains("mutual TLS"), "{robot}");
    let server = help(&["server", "--help"]);
    let about = server.split("Usage:").next().unwrap();
    for command in ["`rearm`", "`stop`", "`estop`", "`reset-estop`"] {
        assert!(about.contains(command), "`amr server --help` does not name {command}: {about}");
    }
}

#[test]
fn no_help_text_points_outside_the_program() {
    let mut pending: Vec<Vec<String>> = vec![Vec::new()];
    let mut seen = 0;
    while let Some(path) = pending.pop() {
        let mut args: Vec<&str> = path.iter().map(String::as_str).collect();
        args.push("--help");
        let text = help(&args);
        seen += 1;
        assert!(!text.contains("../"), "amr {args:?} points outside the working directory: {text}");
        let mentions_issue = text
            .match_indices("issue ")
            .any(|(at, m)| text[at + m.len()..].starts_with(|c: char| c.is_ascii_digit()));
        assert!(!mentions_issue, "amr {args:?} names an issue: {text}");
        for (name, _) in commands(&text) {
            let mut sub = path.clone();
            sub.push(name);
            pending.push(sub);
        }
    }
    assert!(seen > 20, "only {seen} help texts read");
}

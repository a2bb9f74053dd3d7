//! rosbag2's sqlite3 storage (`.db3`), the default storage of ROS 2 up to Humble: one SQLite
//! database per bag file, read here into the same [`Recorded`] messages an MCAP bag gives, so
//! `amr localize --bag` reads both alike.
//!
//! The layout, as rosbag2_storage_default_plugins writes it (`sqlite_storage.cpp`): a table
//! `topics` (`id`, `name`, `type`, `serialization_format`, `offered_qos_profiles`, and from
//! Iron on `type_description_hash`) and a table `messages` (`id`, `topic_id`, `timestamp`: the
//! receive time in ns, `data`: the serialized message); later versions add `schema` and
//! `metadata` tables, which are not needed here. Messages are read in timestamp order.
//!
//! A file that is not an SQLite database, or one without those two tables, is an error that says
//! so. A database that breaks off part way (a bag whose recorder was killed mid-write) gives the
//! messages read up to the damage, and the reason it stopped.

use std::collections::BTreeMap;
use std::path::Path;

use rusqlite::{Connection, OpenFlags};

use crate::read::Recorded;

/// The 16 bytes every SQLite 3 database starts with.
pub const SQLITE_MAGIC: &[u8; 16] = b"SQLite format 3\0";

/// Why a `.db3` file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum Db3Error {
    #[error("not an SQLite database")]
    NotSqlite,
    #[error("an SQLite database, but not a rosbag2 bag (no `{0}` table)")]
    NotABag(&'static str),
    #[error("SQLite: {0}")]
    Sqlite(#[from] rusqlite::Error),
}

/// What was read from one `.db3` file.
#[derive(Debug, Clone, Default)]
pub struct Db3 {
    /// The messages of the wanted topics, in timestamp order.
    pub messages: Vec<Recorded>,
    /// Every topic of the file: name and type.
    pub topics: Vec<(String, String)>,
    /// Why reading stopped before the end, if it did.
    pub stopped: Option<String>,
}

/// Read the messages of the topics `wanted` keeps from the bag file at `path`.
pub fn read(path: &Path, wanted: impl Fn(&str) -> bool) -> Result<Db3, Db3Error> {
    let mut head = [0u8; 16];
    let is_sqlite = std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .is_ok_and(|()| &head == SQLITE_MAGIC);
    if !is_sqlite {
        return Err(Db3Error::NotSqlite);
    }
    let db = Connection::open_with_flags(
        path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )?;
    for table in ["topics", "messages"] {
        let n: i64 = db.query_row(
            "SELECT count(*) FROM sqlite_master WHERE type = 'table' AND name = ?1",
            [table],
            |r| r.get(0),
        )?;
        if n == 0 {
            return Err(Db3Error::NotABag(table));
        }
    }
    // Topic id → (name, type, serialization format).
    let mut topics: BTreeMap<i64, (String, String, String)> = BTreeMap::new();
    let mut q = db.prepare("SELECT id, name, type, serialization_format FROM topics")?;
    let rows =
        q.query_map([], |r| Ok((r.get::<_, i64>(0)?, r.get::<_, String>(1)?, r.get(2)?, r.get(3)?)))?;
    for row in rows {
        let (id, name, ty, format) = row?;
        topics.insert(id, (name, ty, format));
    }
    let mut out =
        Db3 { topics: topics.values().map(|(n, t, _)| (n.clone(), t.clone())).collect(), ..Db3::default() };
    let mut q = db.prepare("SELECT topic_id, timestamp, data FROM messages ORDER BY timestamp, id")?;
    let mut rows = q.query([])?;
    loop {
        let row = match rows.next() {
            Ok(Some(row)) => row,
            Ok(None) => break,
            Err(e) => {
                out.stopped = Some(e.to_string());
                break;
            }
        };
        let (topic_id, stamp, data) =
            match (row.get::<_, i64>(0), row.get::<_, i64>(1), row.get::<_, Vec<u8>>(2)) {
                (Ok(t), Ok(s), Ok(d)) => (t, s, d),
                (Err(e), ..) | (_, Err(e), _) | (.., Err(e)) => {
                    out.stopped = Some(e.to_string());
                    break;
                }
            };
        let Some((name, ty, format)) = topics.get(&topic_id) else { continue };
        if !wanted(name) {
            continue;
        }
        let t = u64::try_from(stamp).unwrap_or(0);
        out.messages.push(Recorded {
            topic: name.clone(),
            schema: ty.clone(),
            encoding: format.clone(),
            log_time_ns: t,
            publish_time_ns: t,
            data,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "tests")]
    use super::*;

    /// A bag as rosbag2 lays it out, written by SQLite here (the end-to-end tests write theirs
    /// with `rosbags`, an independent writer).
    fn bag(path: &Path, rows: &[(i64, i64, &[u8])]) {
        let db = Connection::open(path).unwrap();
        db.execute_batch(
            "CREATE TABLE topics(id INTEGER PRIMARY KEY, name TEXT NOT NULL, type TEXT NOT NULL, \
             serialization_format TEXT NOT NULL, offered_qos_profiles TEXT NOT NULL);
             CREATE TABLE messages(id INTEGER PRIMARY KEY, topic_id INTEGER NOT NULL, \
             timestamp INTEGER NOT NULL, data BLOB NOT NULL);
             INSERT INTO topics VALUES (1, '/scan', 'sensor_msgs/msg/LaserScan', 'cdr', '');
             INSERT INTO topics VALUES (2, '/odom', 'nav_msgs/msg/Odometry', 'cdr', '');",
        )
        .unwrap();
        for (topic, t, data) in rows {
            db.execute(
                "INSERT INTO messages(topic_id, timestamp, data) VALUES (?1, ?2, ?3)",
                (topic, t, data),
            )
            .unwrap();
        }
    }

    #[test]
    fn messages_come_in_timestamp_order_for_the_wanted_topics() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.db3");
        bag(&p, &[(1, 30, b"c"), (2, 10, b"a"), (1, 20, b"b"), (9, 5, b"orphan")]);
        let got = read(&p, |t| t == "/scan").unwrap();
        let seen: Vec<(&str, u64, &[u8])> =
            got.messages.iter().map(|m| (m.topic.as_str(), m.log_time_ns, m.data.as_slice())).collect();
        assert_eq!(seen, [("/scan", 20, b"b".as_slice()), ("/scan", 30, b"c".as_slice())]);
        assert_eq!(got.messages[0].schema, "sensor_msgs/msg/LaserScan");
        assert_eq!(got.messages[0].encoding, "cdr");
        assert_eq!(got.topics.len(), 2);
        assert!(got.stopped.is_none());
        assert_eq!(read(&p, |_| true).unwrap().messages.len(), 3, "a message of no known topic is left out");
    }

    #[test]
    fn other_files_are_refused_by_what_they_are() {
        let dir = tempfile::tempdir().unwrap();
        let text = dir.path().join("notes.db3");
        std::fs::write(&text, "not a database at all").unwrap();
        assert!(matches!(read(&text, |_| true), Err(Db3Error::NotSqlite)));
        let empty = dir.path().join("empty.db3");
        std::fs::write(&empty, "").unwrap();
        assert!(matches!(read(&empty, |_| true), Err(Db3Error::NotSqlite)));
        let other = dir.path().join("other.db3");
        Connection::open(&other).unwrap().execute_batch("CREATE TABLE topics(id INTEGER);").unwrap();
        let e = read(&other, |_| true).unwrap_err();
        assert!(matches!(e, Db3Error::NotABag("messages")), "{e}");
    }

    #[test]
    fn a_damaged_database_is_an_error_or_stops_with_its_reason_and_never_panics() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.db3");
        let big = vec![7u8; 3000];
        let rows: Vec<(i64, i64, &[u8])> = (0..200).map(|k| (1, k, big.as_slice())).collect();
        bag(&p, &rows);
        let whole = std::fs::read(&p).unwrap();
        // Cut at many places, and bytes overwritten at many places: an error or some messages,
        // never a panic, never more than were written.
        for cut in (100..whole.len()).step_by(whole.len() / 40) {
            let damaged = dir.path().join("cut.db3");
            std::fs::write(&damaged, &whole[..cut]).unwrap();
            if let Ok(got) = read(&damaged, |_| true) {
                assert!(got.messages.len() <= 200);
            }
        }
        for at in (100..whole.len()).step_by(whole.len() / 40) {
            let mut bytes = whole.clone();
            for b in bytes.iter_mut().skip(at).take(64) {
                *b ^= 0x5a;
            }
            let damaged = dir.path().join("flipped.db3");
            std::fs::write(&damaged, &bytes).unwrap();
            if let Ok(got) = read(&damaged, |_| true) {
                assert!(got.messages.len() <= 200);
            }
        }
    }
}

//! `amr tools carmen-prepare`: a Radish "corrected" CARMEN log made into the files `amr bench
//! localize` reads (amr_core::carmen::prepare does the work; this reads and writes the files);
//! `amr tools carmen-kidnap`: such a log with kidnappings written into it.

use std::io::Read as _;
use std::path::Path;

use amr_core::carmen::prepare::{MapOptions, prepare};
use amr_core::map::{MapMode, save_map};
use anyhow::Context as _;

/// The name a log's files get: its file name without `.gz`, `.log` and `-corrected`.
fn default_name(log: &Path) -> Option<String> {
    let file = log.file_name()?.to_str()?;
    let file = file.strip_suffix(".gz").unwrap_or(file);
    let file = file.strip_suffix(".log").unwrap_or(file);
    let file = file.strip_suffix("-corrected").unwrap_or(file);
    (!file.is_empty()).then(|| file.to_owned())
}

/// The bytes as they are, or decompressed when they begin with gzip's magic number (the public
/// logs are published as `.log.gz`). Concatenated gzip members are read as one stream.
fn gunzip_if_gzip(bytes: Vec<u8>) -> anyhow::Result<Vec<u8>> {
    if !bytes.starts_with(&[0x1f, 0x8b]) {
        return Ok(bytes);
    }
    let mut out = Vec::with_capacity(bytes.len() * 4);
    flate2::read::MultiGzDecoder::new(bytes.as_slice())
        .read_to_end(&mut out)
        .context("gzip-compressed but not whole (the download may have been cut short)")?;
    Ok(out)
}

/// Write `NAME-raw.log`, `NAME-gt.csv`, `NAME_map.yaml` and `NAME_map.pgm` into `out`.
pub(crate) fn prepare_log(log: &Path, out: &Path, name: Option<String>) -> anyhow::Result<()> {
    let stdin = log == Path::new("-");
    let name = match name {
        Some(n) => n,
        None if stdin => anyhow::bail!("give --name when the log comes on standard input"),
        None => default_name(log).with_context(|| format!("{}: give --name", log.display()))?,
    };
    anyhow::ensure!(
        !name.is_empty() && !name.contains(['/', '\\']) && name != "." && name != "..",
        "--name `{name}`: a file name, without a directory"
    );
    let bytes = if stdin {
        let mut b = Vec::new();
        std::io::stdin().read_to_end(&mut b).context("cannot read standard input")?;
        b
    } else {
        std::fs::read(log).with_context(|| format!("cannot read {}", log.display()))?
    };
    let bytes = gunzip_if_gzip(bytes).with_context(|| log.display().to_string())?;
    let text = String::from_utf8(bytes).with_context(|| format!("{}: not a text file", log.display()))?;
    let p = prepare(&text, &MapOptions::default()).with_context(|| log.display().to_string())?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let image = format!("{name}_map.pgm");
    let (yaml, pgm) = save_map(&p.map, MapMode::Trinary, 0.65, 0.196, &image)?;
    for (file, bytes) in [
        (format!("{name}-raw.log"), p.raw_log.as_bytes()),
        (format!("{name}-gt.csv"), p.reference_csv.as_bytes()),
        (format!("{name}_map.yaml"), yaml.as_bytes()),
        (image, pgm.as_slice()),
    ] {
        let path = out.join(file);
        std::fs::write(&path, bytes).with_context(|| format!("cannot write {}", path.display()))?;
    }
    let count = |v: i8| p.map.cells.iter().filter(|c| **c == v).count();
    tracing::info!(
        log = %name,
        scans = p.scans,
        odometry_lines = p.odometry_lines,
        anchors_dropped = p.anchors,
        map = %format!("{} × {} cells at {} m", p.map.width, p.map.height, p.map.resolution_m),
        occupied = count(amr_core::map::OCCUPIED),
        free = count(amr_core::map::FREE),
        unknown = count(amr_core::map::UNKNOWN),
        "wrote {name}-raw.log, {name}-gt.csv, {name}_map.yaml and {name}_map.pgm to {}",
        out.display()
    );
    Ok(())
}

/// Write `log` with its odometry teleported every `every` scans (jumps from `seed`) to `out`.
pub(crate) fn kidnap_log(log: &Path, every: u64, seed: u64, out: &Path) -> anyhow::Result<()> {
    let every = usize::try_from(every).context("--every is too large")?;
    let text = std::fs::read_to_string(log).with_context(|| format!("cannot read {}", log.display()))?;
    let (written, kidnaps) = amr_core::amcl::log::kidnapped_text(&text, every, seed)
        .map_err(|e| anyhow::anyhow!("{}: {e}", log.display()))?;
    std::fs::write(out, written).with_context(|| format!("cannot write {}", out.display()))?;
    for k in &kidnaps {
        tracing::info!(
            scan = k.scan,
            jump_m = %format!("{:.2}", k.jump.translation_norm()),
            jump_deg = %format!("{:.0}", k.jump.theta.to_degrees()),
            "odometry teleported"
        );
    }
    tracing::info!(kidnappings = kidnaps.len(), "wrote {}", out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_from_file_names() {
        assert_eq!(default_name(Path::new("/x/aces-corrected.log.gz")).as_deref(), Some("aces"));
        assert_eq!(default_name(Path::new("freiburg-079-corrected.log")).as_deref(), Some("freiburg-079"));
        assert_eq!(default_name(Path::new("run.log")).as_deref(), Some("run"));
        assert_eq!(default_name(Path::new("/")), None);
    }

    fn gzip(bytes: &[u8]) -> Vec<u8> {
        use std::io::Write as _;
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(bytes).unwrap();
        e.finish().unwrap()
    }

    #[test]
    fn gzip_input_is_decompressed_and_plain_input_passes_through() {
        let text = b"ODOM 0 0 0 0 0 0 1.0 host 1.0\n".repeat(50);
        assert_eq!(gunzip_if_gzip(text.clone()).unwrap(), text);
        assert_eq!(gunzip_if_gzip(gzip(&text)).unwrap(), text);
        // Two members, as `cat a.gz b.gz` makes them.
        let mut two = gzip(&text[..100]);
        two.extend(gzip(&text[100..]));
        assert_eq!(gunzip_if_gzip(two).unwrap(), text);
    }

    #[test]
    fn a_cut_gzip_file_is_an_error() {
        let text = b"ODOM 0 0 0 0 0 0 1.0 host 1.0\n".repeat(500);
        let z = gzip(&text);
        let err = gunzip_if_gzip(z[..z.len() / 2].to_vec()).unwrap_err();
        assert!(format!("{err:#}").contains("not whole"), "{err:#}");
    }
}

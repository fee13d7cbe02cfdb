//! `bench --near`: a near-light job against the distant job on the same images. The
//! renderer's ring over a relief plate (24 LEDs) is written once per size as two folders,
//! one with the LEDs' positions and one with the best distant table (directions and
//! intensities at the plate's centre); `photostereo reconstruct` runs on each in a child
//! process, timed (wall clock) with its peak resident memory.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use anyhow::Context;
use photostereo::core::synth;

use super::memory;
use super::stats::median;

/// LEDs on the ring.
pub(super) const LEDS: usize = 24;

/// One size's medians.
pub(super) struct Row {
    pub size: usize,
    pub near: (f64, f64),
    pub distant: (f64, f64),
}

/// Each size, `runs` times each way, alternating.
pub(super) fn run(sizes: &[usize], runs: usize, tmp: &Path) -> anyhow::Result<Vec<Row>> {
    let exe = std::env::current_exe().context("finding this executable")?;
    let mut rows = Vec::new();
    for &size in sizes {
        eprintln!("bench: rendering the {size}² ring of {LEDS} LEDs");
        let near = tmp.join(format!("near-{size}"));
        let distant = tmp.join(format!("distant-{size}"));
        write_sets(size, &near, &distant)?;
        let (mut n, mut d) = (Vec::new(), Vec::new());
        for _ in 0..runs {
            n.push(reconstruct(&exe, &near, tmp)?);
            d.push(reconstruct(&exe, &distant, tmp)?);
        }
        let medians = |v: &[(f64, f64)]| {
            let s: Vec<f64> = v.iter().map(|r| r.0).collect();
            let m: Vec<f64> = v.iter().map(|r| r.1).collect();
            (
                median(&s).unwrap_or(f64::NAN),
                median(&m).unwrap_or(f64::NAN),
            )
        };
        rows.push(Row {
            size,
            near: medians(&n),
            distant: medians(&d),
        });
    }
    Ok(rows)
}

/// The ring rendered at `size²` and written twice: with positions into `near`, with the
/// distant table into `distant`. The rendering is dropped before any child starts: a
/// child's peak (`wait4`) counts what this process held when it forked.
fn write_sets(size: usize, near: &Path, distant: &Path) -> anyhow::Result<()> {
    let rig = synth::ring_relief_of(size, LEDS);
    rig.write(near).context("writing the near set")?;
    std::fs::create_dir_all(distant)?;
    let mut csv = String::new();
    for l in rig.distant_table() {
        std::fs::copy(near.join(&l.name), distant.join(&l.name))?;
        let d = l.direction;
        csv += &format!(
            "{}, {}, {}, {}, {}\n",
            l.name, d[0], d[1], d[2], l.intensity
        );
    }
    std::fs::write(distant.join("light_directions.csv"), csv)?;
    Ok(())
}

/// GNU time: the peak of a child it forks itself, from a small process; the bench's own
/// children's `wait4` peaks start at what the bench held when it forked.
const GNU_TIME: &str = "/usr/bin/time";

/// `photostereo reconstruct dir`: seconds and peak bytes (NaN when not measured), the
/// peak through [`GNU_TIME`] when the machine has it.
fn reconstruct(exe: &PathBuf, dir: &Path, tmp: &Path) -> anyhow::Result<(f64, f64)> {
    let log = tmp.join("reconstruct.log");
    let peak_file = tmp.join("peak.txt");
    let stderr = std::fs::File::create(&log).context("creating the child's log")?;
    let timed = Path::new(GNU_TIME).is_file();
    let mut cmd = if timed {
        let mut c = Command::new(GNU_TIME);
        c.arg("-f").arg("%M").arg("-o").arg(&peak_file).arg(exe);
        c
    } else {
        Command::new(exe)
    };
    let start = Instant::now();
    let child = cmd
        .arg("reconstruct")
        .arg(dir)
        .arg("--out")
        .arg(tmp.join("out"))
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .context("starting `photostereo reconstruct`")?;
    let (status, peak) = memory::wait_with_peak(child).context("waiting for it")?;
    let seconds = start.elapsed().as_secs_f64();
    if !status.success() {
        let said = std::fs::read_to_string(&log).unwrap_or_default();
        anyhow::bail!(
            "`photostereo reconstruct` failed ({status}): {}",
            said.trim()
        );
    }
    let peak = if timed {
        let text = std::fs::read_to_string(&peak_file).unwrap_or_default();
        text.trim()
            .parse::<f64>()
            .map_or(f64::NAN, |kib| kib * 1024.0)
    } else {
        peak.unwrap_or(f64::NAN)
    };
    Ok((seconds, peak))
}

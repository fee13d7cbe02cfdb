//! A job's `archive` part: a zip of a folder in one of the layouts `core::layout` reads,
//! unpacked into the staging directory under the size caps, its entries' paths checked.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Write};
use std::path::{Component, Path};

use crate::core::camera::{self, Pinhole};
use crate::core::error::InputError;
use crate::core::layout;
use crate::core::lights;
use crate::service::config::{Config, MAX_LIGHTS_BYTES};
use crate::service::error::ApiError;
use crate::service::store::{MASK_FILE, image_file};

use super::checks::{MAX_CAMERA_BYTES, StoredImage, parse_camera, probe_image};
use super::form::{HEAD_BYTES, too_much_input};

/// Bounds on what an archive may unpack to.
#[derive(Debug, Clone, Copy)]
pub(crate) struct ArchiveLimits {
    max_entries: usize,
    max_unpacked: u64,
    max_images: usize,
    max_pixels: u64,
    max_input_bytes: u64,
}

impl From<&Config> for ArchiveLimits {
    fn from(c: &Config) -> Self {
        Self {
            max_entries: c.max_parts,
            max_unpacked: c.max_unpacked_bytes,
            max_images: c.max_images,
            max_pixels: c.max_pixels,
            max_input_bytes: c.max_input_bytes,
        }
    }
}

/// macOS and editor leftovers that are skipped rather than refused.
fn is_junk(components: &[String]) -> bool {
    components
        .iter()
        .any(|c| c == "__MACOSX" || c.starts_with('.'))
}

fn zip_error(entry: &str, e: zip::result::ZipError) -> ApiError {
    match e {
        zip::result::ZipError::UnsupportedArchive(what) => {
            ApiError::unsupported_media(format!("archive entry {entry:?} cannot be read: {what}"))
        }
        zip::result::ZipError::CompressionMethodNotSupported(m) => {
            ApiError::unsupported_media(format!(
                "archive entry {entry:?} uses compression method {m}; only stored and deflate are supported"
            ))
        }
        other => ApiError::invalid(format!("archive entry {entry:?} cannot be read: {other}")),
    }
}

/// What an archive unpacked to.
pub(crate) struct Unpacked {
    /// The images its table names, in archive order.
    pub(crate) images: Vec<StoredImage>,
    /// Its light table, as JSON in the project's frame ([`lights::to_json`]); a table
    /// giving positions, as the archive holds it.
    pub(crate) table: Vec<u8>,
    /// Its `mask.png`, when asked for and present.
    pub(crate) mask: Option<StoredImage>,
    /// Whether it holds a `mask.png` (used or not).
    pub(crate) has_mask: bool,
    /// Its camera file (`camera.json`, else `K.txt`): the name and the camera.
    pub(crate) camera: Option<(String, Pinhole)>,
    pub(crate) notes: Vec<String>,
}

/// Unpack a zip of a folder in one of the layouts [`layout`] reads (at the top of the
/// archive or in one folder) into `dir`: its table files are read, then the images the
/// table names (and its `mask.png` when `want_mask`) streamed out under the size caps;
/// every other entry is skipped.
pub(crate) fn extract_archive(
    path: &Path,
    dir: &Path,
    limits: &ArchiveLimits,
    want_mask: bool,
) -> Result<Unpacked, ApiError> {
    let file = File::open(path)?;
    let mut zip = zip::ZipArchive::new(BufReader::new(file))
        .map_err(|e| ApiError::invalid(format!("the archive is not a readable zip file: {e}")))?;
    if zip.len() > limits.max_entries {
        return Err(ApiError::too_large(format!(
            "the archive has {} entries, over the limit of {}",
            zip.len(),
            limits.max_entries
        )));
    }

    // Pass 1: names only. Refuse unsafe paths and links; find the layout.
    let mut entries: Vec<(usize, Vec<String>)> = Vec::new();
    for i in 0..zip.len() {
        let entry = zip
            .by_index_data(i)
            .map_err(|e| zip_error(&format!("#{i}"), e))?;
        let raw = entry
            .name()
            .map(|n| n.into_owned())
            .unwrap_or_else(|_| format!("#{i}"));
        let unsafe_path = || {
            ApiError::invalid(format!(
                "archive entry {raw:?} has an unsafe path (absolute, or leading out of the archive)"
            ))
        };
        let absolute =
            raw.starts_with('/') || raw.starts_with('\\') || raw.as_bytes().get(1) == Some(&b':');
        if absolute {
            return Err(unsafe_path());
        }
        let enclosed = entry.enclosed_name().ok_or_else(unsafe_path)?;
        let mut components = Vec::new();
        for c in enclosed.components() {
            match c {
                Component::Normal(s) => components.push(s.to_string_lossy().into_owned()),
                Component::CurDir => {}
                _ => return Err(unsafe_path()),
            }
        }
        if entry.is_dir() || components.is_empty() || is_junk(&components) {
            continue;
        }
        if entry.is_symlink() {
            return Err(ApiError::invalid(format!(
                "archive entry {raw:?} is a symbolic link"
            )));
        }
        entries.push((i, components));
    }
    if entries.is_empty() {
        return Err(ApiError::invalid("the archive holds no files"));
    }
    let flat = entries.iter().all(|(_, c)| c.len() == 1);
    if !flat {
        let top = &entries[0].1[0];
        if let Some((_, c)) = entries.iter().find(|(_, c)| c.len() != 2 || &c[0] != top) {
            return Err(ApiError::invalid(format!(
                "archive entry {:?} is out of place: the images and the light table must be at the top of the archive or all inside one folder",
                c.join("/")
            )));
        }
    }
    let mut by_name: HashMap<String, usize> = HashMap::new();
    for (i, components) in &entries {
        let name = components.last().cloned().unwrap_or_default();
        if by_name.insert(name.clone(), *i).is_some() {
            return Err(ApiError::invalid(format!(
                "the archive holds {name:?} more than once"
            )));
        }
    }

    let mut budget = limits.max_unpacked;
    // The images' and the mask's bytes, as stored for the job.
    let mut stored = 0u64;
    let over_budget = || {
        ApiError::too_large(format!(
            "the archive unpacks to more than {} bytes",
            limits.max_unpacked
        ))
    };
    // The table files first: they say which entries are wanted.
    let mut texts: HashMap<&str, Vec<u8>> = HashMap::new();
    let mut tables: Vec<(&str, usize)> = (by_name.iter())
        .filter(|(n, _)| layout::is_table_file(n))
        .map(|(n, &i)| (n.as_str(), i))
        .collect();
    tables.sort();
    for (name, i) in tables {
        let what = format!("the light table file {name:?}");
        let bytes = read_entry(
            &mut zip,
            i,
            (name, &what),
            MAX_LIGHTS_BYTES,
            &mut budget,
            &over_budget,
        )?;
        texts.insert(name, bytes);
    }
    let mut names: Vec<String> = by_name.keys().cloned().collect();
    names.sort();
    let table = layout::read_table("the archive", &names, &mut |n| {
        Ok(texts.get(n).cloned().unwrap_or_default())
    })?;
    let named: std::collections::HashSet<&str> =
        table.lights.iter().map(|l| l.name.as_str()).collect();
    if named.len() > limits.max_images {
        return Err(InputError::TooManyImages {
            count: named.len(),
            limit: limits.max_images,
        }
        .into());
    }
    // A table of directions is stored as JSON in the project's frame; one that gives
    // positions (only light_directions.json can) as it came, rig and all, for the job to
    // read back with `lights::parse_table`.
    let stored_table = if table.lights.iter().any(|l| l.emitter.is_some()) {
        texts.get(layout::SEED_JSON).cloned().unwrap_or_default()
    } else {
        lights::to_json(&table.lights)
    };
    let mask_name = table.mask.as_deref().filter(|_| want_mask);
    let camera = match camera::FILES.iter().find(|n| by_name.contains_key(**n)) {
        Some(name) => {
            let what = format!("{name} in the archive");
            let index = by_name[*name];
            let bytes = read_entry(
                &mut zip,
                index,
                (name, &what),
                MAX_CAMERA_BYTES,
                &mut budget,
                &over_budget,
            )?;
            Some((name.to_string(), parse_camera(&bytes, &what)?))
        }
        None => None,
    };

    // Then the images the table names, and the mask, in archive order.
    let mut images = Vec::new();
    let mut mask = None;
    let mut buf = vec![0u8; 64 * 1024];
    for (i, components) in entries {
        let name = components.last().cloned().unwrap_or_default();
        let is_mask = mask_name == Some(name.as_str());
        if !(named.contains(name.as_str()) || is_mask) {
            continue;
        }
        let mut entry = zip.by_index(i).map_err(|e| zip_error(&name, e))?;
        if entry.size() > budget {
            return Err(over_budget());
        }
        let file = if is_mask {
            MASK_FILE.to_string()
        } else {
            image_file(images.len())
        };
        let target = dir.join(&file);
        let mut out = File::create(&target)?;
        let mut head = Vec::with_capacity(HEAD_BYTES);
        loop {
            let n = match entry.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
                Err(e) => {
                    return Err(ApiError::invalid(format!(
                        "archive entry {name:?} cannot be read: {e}"
                    )));
                }
            };
            if n as u64 > budget {
                return Err(over_budget());
            }
            budget -= n as u64;
            stored += n as u64;
            if stored > limits.max_input_bytes {
                return Err(too_much_input(&name, limits.max_input_bytes));
            }
            if head.len() < HEAD_BYTES {
                let take = (HEAD_BYTES - head.len()).min(n);
                head.extend_from_slice(&buf[..take]);
            }
            out.write_all(&buf[..n])?;
        }
        out.flush()?;
        drop(out);
        let probed = probe_image(&target, &name, &head, limits.max_pixels);
        if is_mask {
            let (width, height, depth) =
                probed.map_err(|e| ApiError::invalid(format!("mask: {e}")))?;
            mask = Some(StoredImage {
                name,
                file,
                width,
                height,
                depth,
            });
            continue;
        }
        let (width, height, depth) = probed?;
        images.push(StoredImage {
            name,
            file,
            width,
            height,
            depth,
        });
    }
    Ok(Unpacked {
        images,
        table: stored_table,
        mask,
        has_mask: table.mask.is_some(),
        camera,
        notes: table.notes,
    })
}

/// A small entry (a table or camera file: its name, and what it is for a refusal) read
/// whole, within `limit` bytes and the archive's unpacking `budget`.
fn read_entry(
    zip: &mut zip::ZipArchive<BufReader<File>>,
    index: usize,
    (name, what): (&str, &str),
    limit: usize,
    budget: &mut u64,
    over_budget: &dyn Fn() -> ApiError,
) -> Result<Vec<u8>, ApiError> {
    let mut entry = zip.by_index(index).map_err(|e| zip_error(name, e))?;
    if entry.size() > *budget {
        return Err(over_budget());
    }
    let mut bytes = Vec::new();
    (&mut entry)
        .take(limit as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| ApiError::invalid(format!("archive entry {name:?} cannot be read: {e}")))?;
    if bytes.len() > limit {
        return Err(ApiError::too_large(format!(
            "{what} is larger than {limit} bytes"
        )));
    }
    *budget -= bytes.len() as u64;
    Ok(bytes)
}

/// The archive reader on its own, for property tests and fuzzing: unpack the zip file at
/// `zip` into the directory `dir` under `config`'s caps (`max_parts` entries,
/// `max_unpacked_bytes`, `max_images`, `max_pixels`, `max_input_bytes`), exactly as an `archive` part is
/// unpacked. Returns the images' names (in archive order) and the light table's bytes
/// (as stored for the job: JSON in the project's frame).
pub fn unpack_archive(
    zip: &Path,
    dir: &Path,
    config: &Config,
) -> Result<(Vec<String>, Vec<u8>), ApiError> {
    let unpacked = extract_archive(zip, dir, &ArchiveLimits::from(config), true)?;
    let names = unpacked.images.into_iter().map(|i| i.name).collect();
    Ok((names, unpacked.table))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;
    use zip::write::SimpleFileOptions;

    fn png(w: u32, h: u32) -> Vec<u8> {
        let img = image::GrayImage::from_pixel(w, h, image::Luma([128]));
        let mut out = Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).unwrap();
        out.into_inner()
    }

    fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
        let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
        for (name, data) in entries {
            w.start_file(*name, SimpleFileOptions::default()).unwrap();
            w.write_all(data).unwrap();
        }
        w.finish().unwrap().into_inner()
    }

    fn limits() -> ArchiveLimits {
        ArchiveLimits {
            max_entries: 16,
            max_unpacked: 1 << 20,
            max_images: 8,
            max_pixels: 1 << 20,
            max_input_bytes: 1 << 20,
        }
    }

    fn extract(bytes: &[u8], limits: &ArchiveLimits) -> Result<Vec<String>, ApiError> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.zip");
        std::fs::write(&path, bytes).unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        extract_archive(&path, &out, limits, true)
            .map(|u| u.images.into_iter().map(|i| i.name).collect())
    }

    const TABLE: &[u8] = b"a.png, 0, 0, 1\nb.png, 1, 0, 1\nc.png, 0, 1, 1\n";

    #[test]
    fn accepts_flat_and_one_folder_and_skips_junk() {
        let p = png(4, 4);
        let flat = zip_of(&[
            ("a.png", &p),
            ("light_directions.csv", TABLE),
            ("__MACOSX/._a.png", b"x"),
        ]);
        assert_eq!(extract(&flat, &limits()).unwrap(), ["a.png"]);
        let nested = zip_of(&[
            ("set/a.png", &p),
            ("set/b.png", &p),
            ("set/light_directions.csv", TABLE),
            ("set/.DS_Store", b"x"),
            ("set/notes.txt", b"not named: skipped"),
            ("set/other.png", b"not named: skipped"),
        ]);
        assert_eq!(extract(&nested, &limits()).unwrap(), ["a.png", "b.png"]);
    }

    #[test]
    fn an_archive_may_bring_an_lp_table() {
        let p = png(4, 4);
        let lp = b"3\r\n./jpeg-exports/a.png 0 0 1\r\nC:\\rti\\b.png 1 0 1\r\nc.png 0 1 1\r\n";
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.zip");
        let zip = zip_of(&[
            ("set/a.png", &p),
            ("set/b.png", &p),
            ("set/c.png", &p),
            ("set/rti.lp", lp),
        ]);
        std::fs::write(&path, zip).unwrap();
        let u = extract_archive(&path, dir.path(), &limits(), true).unwrap();
        let names: Vec<&str> = u.images.iter().map(|i| i.name.as_str()).collect();
        assert_eq!(names, ["a.png", "b.png", "c.png"]);
        // Stored in the project's frame: y up in the file is −y here.
        let stored = lights::parse_bytes(&u.table).unwrap();
        assert!(
            (stored[2].direction[1] + 0.5f64.sqrt()).abs() < 1e-15,
            "{stored:?}"
        );
        let e = extract(
            &zip_of(&[("a.png", &p), ("x.lp", lp), ("y.lp", lp)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("2 .lp files"), "{e}");
    }

    #[test]
    fn an_archive_brings_its_camera_file_json_first() {
        let p = png(4, 4);
        let k = b"8 0 1.5\n0 8 1.5\n0 0 1\n";
        let json = br#"{"fx": 9, "fy": 9, "cx": 1.5, "cy": 1.5}"#;
        let camera = |entries: &[(&str, &[u8])]| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("a.zip");
            std::fs::write(&path, zip_of(entries)).unwrap();
            extract_archive(&path, dir.path(), &limits(), true).map(|u| u.camera)
        };
        let base = [("a.png", &p[..]), ("light_directions.csv", TABLE)];
        let (name, k_txt) = camera(&[base[0], base[1], ("K.txt", k)]).unwrap().unwrap();
        assert_eq!((name.as_str(), k_txt.fx, k_txt.cx), ("K.txt", 8.0, 1.5));
        let both = camera(&[base[0], base[1], ("K.txt", k), ("camera.json", json)]);
        assert_eq!(both.unwrap().unwrap().1.fx, 9.0);
        assert!(camera(&base).unwrap().is_none());
        let e = camera(&[base[0], base[1], ("K.txt", b"8 8")]).unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(
            e.detail().contains("K.txt in the archive") && e.detail().contains("2 numbers"),
            "{e}"
        );
        let e = camera(&[base[0], base[1], ("K.txt", &[b' '; 5000][..])]).unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
    }

    #[test]
    fn refuses_unsafe_layouts_junk_and_bombs() {
        let p = png(4, 4);
        let e = extract(
            &zip_of(&[("../a.png", &p), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 422);
        assert!(e.detail().contains("unsafe path"), "{e}");
        let e = extract(
            &zip_of(&[("/etc/a.png", &p), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("unsafe path"), "{e}");
        let e = extract(
            &zip_of(&[("x/a.png", &p), ("y/light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert!(e.detail().contains("out of place"), "{e}");
        let e = extract(
            &zip_of(&[
                ("a.png", b"hello"),
                ("notes.txt", b"hello"),
                ("light_directions.csv", TABLE),
            ]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 415, "{e}");
        assert!(e.detail().contains("a.png"), "{e}");
        let e = extract(&zip_of(&[("a.png", &p)]), &limits()).unwrap_err();
        assert!(e.detail().contains("light_directions.csv"), "{e}");
        // 4 MiB of zeros compresses to a few KiB: the cap stops it while streaming.
        let zeros = vec![0u8; 4 << 20];
        let e = extract(
            &zip_of(&[("a.png", &zeros), ("light_directions.csv", TABLE)]),
            &limits(),
        )
        .unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
        let many: Vec<(String, Vec<u8>)> =
            (0..20).map(|i| (format!("{i}.png"), p.clone())).collect();
        let refs: Vec<(&str, &[u8])> = many
            .iter()
            .map(|(n, d)| (n.as_str(), d.as_slice()))
            .collect();
        let e = extract(&zip_of(&refs), &limits()).unwrap_err();
        assert_eq!(e.status().as_u16(), 413, "{e}");
        let e = extract(b"PK\x03\x04 not really a zip", &limits()).unwrap_err();
        assert_eq!(e.status().as_u16(), 422, "{e}");
    }
}

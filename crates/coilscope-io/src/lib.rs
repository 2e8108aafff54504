//! # coilscope-io
//!
//! Files at the edge of coilscope, per `docs/formats.md`:
//!
//! * Recordings: WAV, channel 1 voltage (V), channel 2 current (A), optional channel 3
//!   displacement (m, + = coil out). 32-bit float holds physical units; integer PCM (or float
//!   in other units) needs scale factors, from a sidecar `NAME.wav.json`
//!   `{"scale": [V per unit, A per unit, m per unit]}` or from the caller. For integer PCM a
//!   "unit" is one integer count of the stored sample.
//! * Parameter sets: an embedded driver name or a JSON file.
//! * Impedance curves ([`impedance`]): `.zma`, `.frd`/`.txt` and CSV with named columns,
//!   as REW, ARTA, LIMP, DATS and Klippel write them.
//! * Every write is atomic (temporary file in the same directory, fsync, rename): a crash
//!   never leaves a half-written file under the final name.
//!
//! Every error is one line naming the file, the channel or key, the value, and what would
//! be valid.

pub mod export;
pub mod impedance;
pub mod protection;

use coilscope_core::params::{embedded_driver, embedded_driver_names, Parameters};
use std::fmt;
use std::io::Write;
use std::path::{Path, PathBuf};

/// A file problem, as one readable line.
#[derive(Debug, Clone, PartialEq)]
pub struct IoError(pub String);

impl fmt::Display for IoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for IoError {}

fn err<T>(msg: impl Into<String>) -> Result<T, IoError> {
    Err(IoError(msg.into()))
}

/// Where a write to a path goes, symlinks followed.
enum Target {
    /// An existing FIFO or character device (`/dev/null`, `/dev/stdout`, a pipe): written
    /// straight.
    Stream(PathBuf),
    /// A regular file, existing or new: replaced atomically from a temporary file in `dir`.
    File { path: PathBuf, dir: PathBuf, name: String },
}

/// Resolve `path` for writing, or say why it cannot be written.
fn write_target(path: &Path) -> Result<Target, IoError> {
    use std::os::unix::fs::FileTypeExt;
    // Follow symlinks (a chain of them) to the file that is really written.
    let mut target = path.to_path_buf();
    for _ in 0..40 {
        match std::fs::symlink_metadata(&target) {
            Ok(m) if m.file_type().is_symlink() => {
                let link = std::fs::read_link(&target)
                    .map_err(|e| IoError(format!("{}: cannot read the symlink ({e})", target.display())))?;
                target = if link.is_absolute() { link } else { target.parent().unwrap_or(Path::new(".")).join(link) };
            }
            _ => break,
        }
    }
    if let Ok(m) = std::fs::metadata(&target) {
        let t = m.file_type();
        if t.is_fifo() || t.is_char_device() {
            return Ok(Target::Stream(target));
        }
        if !t.is_file() {
            let what = if t.is_dir() {
                "a directory"
            } else if t.is_block_device() {
                "a block device"
            } else if t.is_socket() {
                "a socket"
            } else {
                "not a regular file"
            };
            return err(format!("{}: is {what}; give the path of a file to write", path.display()));
        }
    }
    let dir = match target.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !dir.is_dir() {
        return err(format!("{}: the directory {} does not exist", path.display(), dir.display()));
    }
    // The devices' directory holds devices, not results: a regular file there (`/dev/null.zma`
    // beside `--out /dev/null`) is refused; an existing device is written above.
    if std::fs::canonicalize(&dir).is_ok_and(|d| d.starts_with("/dev")) {
        return err(format!(
            "{}: a regular file in {}, the devices' directory; give a path elsewhere (an existing device such as /dev/null is written straight)",
            path.display(),
            dir.display()
        ));
    }
    let name = target.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    if name.is_empty() {
        return err(format!("{}: not a file path", path.display()));
    }
    Ok(Target::File { path: target, dir, name })
}

/// Check, before the work, that [`atomic_write`] can write `path`: its directory exists, it
/// is not a directory or another special file, and it is not a regular file among the devices.
pub fn check_writable(path: &Path) -> Result<(), IoError> {
    write_target(path).map(|_| ())
}

/// Check, before the work, a command's output `out` and the files it writes beside it
/// (`beside`, derived from its name: a `.zma`, a description). Returns whether those are to
/// be written: not beside an existing FIFO or character device (symlinks followed) such as
/// `/dev/null`, which [`atomic_write`] writes straight and where they have nowhere to go.
pub fn check_outputs(out: &Path, beside: &[PathBuf]) -> Result<bool, IoError> {
    if let Target::Stream(_) = write_target(out)? {
        return Ok(false);
    }
    beside.iter().try_for_each(|p| check_writable(p))?;
    Ok(true)
}

/// Write `bytes` to `path` atomically: a temporary file beside the target, synced, then
/// renamed over it, so a reader sees the old file or the new one, never half of one.
///
/// * A symlink is followed: its target is replaced atomically, the link stays.
/// * A FIFO or character device (`/dev/null`, `/dev/stdout`, a pipe) is written straight
///   (there is nothing to replace atomically, and replacing it would destroy it).
/// * Any other special file (block device, socket, directory) is refused, and so is a
///   regular file in `/dev`.
pub fn atomic_write(path: &Path, bytes: &[u8]) -> Result<(), IoError> {
    let (target, dir, name) = match write_target(path)? {
        Target::Stream(target) => {
            return std::fs::OpenOptions::new()
                .write(true)
                .open(&target)
                .and_then(|mut f| f.write_all(bytes))
                .map_err(|e| IoError(format!("{}: cannot write ({e})", path.display())));
        }
        Target::File { path, dir, name } => (path, dir, name),
    };
    // A temporary file of its own beside the target (`tempfile`: a new name each time, so
    // that writers in one process never share one; removed if anything fails), with the
    // permissions of a plain create (0666 less the umask) rather than a temporary file's
    // owner-only ones.
    let result = (|| {
        use std::os::unix::fs::PermissionsExt;
        let mut f = tempfile::Builder::new()
            .prefix(&format!(".{name}."))
            .suffix(".tmp")
            .permissions(std::fs::Permissions::from_mode(0o666))
            .tempfile_in(&dir)?;
        f.write_all(bytes)?;
        f.as_file().sync_all()?;
        f.persist(&target).map(|_| ()).map_err(|e| e.error)
    })();
    result.map_err(|e| IoError(format!("{}: cannot write ({e})", path.display())))
}

/// Write pretty JSON atomically (a JSON value, or a typed file such as
/// [`coilscope_core::result::ResultFile`]).
pub fn write_json<T: serde::Serialize + ?Sized>(path: &Path, value: &T) -> Result<(), IoError> {
    let mut text = serde_json::to_string_pretty(value).expect("maps with string keys always serialise");
    text.push('\n');
    atomic_write(path, text.as_bytes())
}

/// A recording in physical units.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    pub fs: u32,
    /// Terminal voltage (V).
    pub u: Vec<f64>,
    /// Current into the transducer (A).
    pub i: Vec<f64>,
    /// Voice-coil displacement (m, + = coil out), from a laser, if recorded.
    pub x: Option<Vec<f64>>,
}

const CHANNEL_NAMES: [&str; 3] = ["voltage (channel 1)", "current (channel 2)", "displacement (channel 3)"];

/// Raw channels of a WAV file, scaled to physical units.
struct Channels {
    fs: u32,
    data: Vec<Vec<f64>>,
}

/// The sidecar's name for a recording shown as `shown` (messages).
fn sidecar_name(shown: &str) -> String {
    format!("{shown}.json")
}

fn sidecar_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".json");
    PathBuf::from(s)
}

/// Scale factors from the sidecar `NAME.wav.json`, if it exists.
pub fn read_sidecar_scale(path: &Path) -> Result<Option<Vec<f64>>, IoError> {
    let side = sidecar_path(path);
    if !side.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&side).map_err(|e| IoError(format!("{}: cannot read ({e})", side.display())))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
        IoError(format!("{}: not valid JSON ({e}); expected {{\"scale\": [V, A, m per unit]}}", side.display()))
    })?;
    let Some(arr) = v.get("scale").and_then(|s| s.as_array()) else {
        return err(format!(
            "{}: key `scale`: missing or not an array; expected {{\"scale\": [V, A, m per unit]}}",
            side.display()
        ));
    };
    let mut out = Vec::new();
    for (k, item) in arr.iter().enumerate() {
        match item.as_f64() {
            Some(f) if f.is_finite() && f != 0.0 => out.push(f),
            _ => {
                return err(format!(
                    "{}: key `scale`: entry {} is {item}; expected a finite, non-zero number",
                    side.display(),
                    k + 1
                ))
            }
        }
    }
    if out.is_empty() || out.len() > 3 {
        return err(format!(
            "{}: key `scale`: {} entries; expected 1 to 3 (V, A, m per unit)",
            side.display(),
            out.len()
        ));
    }
    Ok(Some(out))
}

fn read_channels(path: &Path, scale: Option<&[f64]>, max_channels: usize) -> Result<Channels, IoError> {
    let shown = path.display();
    if !path.exists() {
        return err(format!("{shown}: no such file"));
    }
    let reader =
        hound::WavReader::open(path).map_err(|e| IoError(format!("{shown}: not a readable WAV file ({e})")))?;
    let sidecar = read_sidecar_scale(path)?;
    let file_len = std::fs::metadata(path).map(|m| m.len()).unwrap_or(u64::MAX);
    channels_from(reader, &shown.to_string(), scale.map(|s| s.to_vec()).or(sidecar), max_channels, file_len)
}

/// Read a recording from the bytes of a WAV file (2 or 3 channels); `name` names it in
/// messages, `scale` gives the physical units of integer PCM. Never panics, whatever the
/// bytes (a fuzz target).
pub fn read_recording_bytes(bytes: &[u8], name: &str, scale: Option<&[f64]>) -> Result<Recording, IoError> {
    let reader = hound::WavReader::new(std::io::Cursor::new(bytes))
        .map_err(|e| IoError(format!("{name}: not a readable WAV file ({e})")))?;
    let ch = channels_from(reader, name, scale.map(|s| s.to_vec()), 3, bytes.len() as u64)?;
    recording_of(ch, name)
}

fn channels_from<R: std::io::Read>(
    mut reader: hound::WavReader<R>,
    shown: &str,
    scale: Option<Vec<f64>>,
    max_channels: usize,
    file_len: u64,
) -> Result<Channels, IoError> {
    let spec = reader.spec();
    let nch = spec.channels as usize;
    if nch == 0 || nch > max_channels {
        return err(format!(
            "{shown}: {nch} channels; expected 1 to {max_channels} (1 voltage V, 2 current A, 3 displacement m)"
        ));
    }
    if !(1000..=1_000_000).contains(&spec.sample_rate) {
        return err(format!("{shown}: sample rate {} Hz is not valid (1 kHz .. 1 MHz)", spec.sample_rate));
    }
    let is_float = spec.sample_format == hound::SampleFormat::Float;
    if let Some(s) = &scale {
        if s.len() < nch {
            return err(format!(
                "{shown}: {} scale factors for {nch} channels; give one per channel (V, A, m per unit)",
                s.len()
            ));
        }
    } else if !is_float {
        return err(format!("{shown}: {}-bit integer PCM needs scale factors: a sidecar {} with {{\"scale\": [V, A, m per count]}}, or --scale", spec.bits_per_sample, sidecar_name(shown)));
    }
    // The header's length is a claim: never reserve more than the file can hold.
    let frames = (reader.duration() as u64)
        .min(file_len / (nch as u64 * (spec.bits_per_sample as u64).div_ceil(8).max(1))) as usize;
    let mut data: Vec<Vec<f64>> = (0..nch).map(|_| Vec::with_capacity(frames)).collect();
    let mut push = |k: usize, v: f64| -> Result<(), IoError> {
        let ch = k % nch;
        if !v.is_finite() {
            let n = k / nch;
            return err(format!(
                "{shown}: {} sample {n} (t = {:.6} s) is {v}; samples must be finite",
                CHANNEL_NAMES[ch],
                n as f64 / spec.sample_rate as f64
            ));
        }
        data[ch].push(v);
        Ok(())
    };
    if is_float {
        if spec.bits_per_sample != 32 {
            return err(format!("{shown}: {}-bit float is not supported; use 32-bit float", spec.bits_per_sample));
        }
        for (k, s) in reader.samples::<f32>().enumerate() {
            push(k, s.map_err(|e| IoError(format!("{shown}: damaged sample data ({e})")))? as f64)?;
        }
    } else {
        for (k, s) in reader.samples::<i32>().enumerate() {
            push(k, s.map_err(|e| IoError(format!("{shown}: damaged sample data ({e})")))? as f64)?;
        }
    }
    if data[0].is_empty() {
        return err(format!("{shown}: no samples"));
    }
    if data.iter().any(|c| c.len() != data[0].len()) {
        return err(format!("{shown}: truncated: the channels have different lengths"));
    }
    if let Some(s) = &scale {
        for (c, f) in data.iter_mut().zip(s) {
            c.iter_mut().for_each(|v| *v *= f);
        }
    }
    Ok(Channels { fs: spec.sample_rate, data })
}

/// Read a recording (2 or 3 channels). `scale` overrides the sidecar.
pub fn read_recording(path: &Path, scale: Option<&[f64]>) -> Result<Recording, IoError> {
    let ch = read_channels(path, scale, 3)?;
    recording_of(ch, &path.display().to_string())
}

fn recording_of(ch: Channels, shown: &str) -> Result<Recording, IoError> {
    if ch.data.len() < 2 {
        return err(format!("{shown}: 1 channel; a recording needs voltage (channel 1, V) and current (channel 2, A)"));
    }
    let mut it = ch.data.into_iter();
    let u = it.next().unwrap_or_default();
    let i = it.next().unwrap_or_default();
    let x = it.next();
    if let Some(x) = &x {
        // A dead laser: a channel 3 that does not move would give a singular or silently
        // wrong scale.
        let mean = x.iter().sum::<f64>() / x.len().max(1) as f64;
        let sd = (x.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / x.len().max(1) as f64).sqrt();
        if !(sd > 1e-12) {
            return err(format!("{shown}: channel 3 (displacement) is silent (sd {sd:.2e} m): the laser is dead, unplugged or out of range; fix it, or record without channel 3 and give --mms KG"));
        }
    }
    Ok(Recording { fs: ch.fs, u, i, x })
}

/// Read a voltage signal (channel 1, V) to drive a simulation; further channels are ignored.
pub fn read_voltage(path: &Path, scale: Option<&[f64]>) -> Result<(u32, Vec<f64>), IoError> {
    let ch = read_channels(path, scale, 3)?;
    Ok((ch.fs, ch.data.into_iter().next().unwrap_or_default()))
}

/// Write channels of equal length as an interleaved 32-bit float WAV (atomically).
fn write_float_wav(path: &Path, fs: u32, channels: &[&[f64]]) -> Result<(), IoError> {
    let n = channels.first().map_or(0, |c| c.len());
    let spec = hound::WavSpec {
        channels: channels.len() as u16,
        sample_rate: fs,
        bits_per_sample: 32,
        sample_format: hound::SampleFormat::Float,
    };
    let mut buf = std::io::Cursor::new(Vec::with_capacity(n * channels.len() * 4 + 64));
    {
        let mut w = hound::WavWriter::new(&mut buf, spec).map_err(|e| IoError(format!("{}: {e}", path.display())))?;
        for k in 0..n {
            for c in channels {
                w.write_sample(c[k] as f32).map_err(|e| IoError(format!("{}: {e}", path.display())))?;
            }
        }
        w.finalize().map_err(|e| IoError(format!("{}: {e}", path.display())))?;
    }
    atomic_write(path, buf.get_ref())
}

/// Write a recording as 32-bit float WAV in physical units (atomically).
pub fn write_recording(path: &Path, rec: &Recording) -> Result<(), IoError> {
    match &rec.x {
        Some(x) => write_float_wav(path, rec.fs, &[&rec.u, &rec.i, x]),
        None => write_float_wav(path, rec.fs, &[&rec.u, &rec.i]),
    }
}

/// Write a voltage signal (V) as a mono 32-bit float WAV (atomically): what `simulate
/// --input` and [`read_voltage`] read back.
pub fn write_voltage(path: &Path, fs: u32, u: &[f64]) -> Result<(), IoError> {
    write_float_wav(path, fs, &[u])
}

/// A parameter set from an embedded driver name, a population name (`population:SEED`,
/// `population:CLASS:SEED`: [`coilscope_core::population`]) or a JSON file path.
pub fn load_parameters(spec: &str) -> Result<Parameters, IoError> {
    if let Some(p) = embedded_driver(spec) {
        return Ok(p);
    }
    if let Some(draw) = coilscope_core::population::parse_name(spec) {
        return draw.map(|d| d.natural()).map_err(IoError);
    }
    let path = Path::new(spec);
    if !path.exists() {
        return err(format!("{spec}: neither an embedded driver ({}) nor an existing parameter file (nor a drawn driver, population:SEED)", embedded_driver_names().join(", ")));
    }
    let text = std::fs::read_to_string(path).map_err(|e| IoError(format!("{spec}: cannot read ({e})")))?;
    let p = Parameters::from_json_str(&text, spec).map_err(|e| IoError(e.to_string()))?;
    // A file from a user's hands: a misspelt key is said at once (the set still loads).
    for (key, meant) in p.near_miss_keys() {
        eprintln!(
            "warning: {spec}: key `{key}` is not one coilscope reads (kept in the file as is); did you mean `{meant}`?"
        );
    }
    Ok(p)
}

/// A box (`enclosure`, see `docs/formats.md`) from a JSON file: the box object itself
/// (`{"type": "vented", "Vb": 0.02, ...}`), an object with an `enclosure` key (a parameter
/// set), or one with `world.enclosure` (a recording's description). Errors name the file and
/// the key.
pub fn load_enclosure(path: &Path) -> Result<coilscope_core::enclosure::Enclosure, IoError> {
    let shown = path.display();
    let text = std::fs::read_to_string(path).map_err(|e| IoError(format!("{shown}: cannot read ({e})")))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
        IoError(format!(
            "{shown}: not valid JSON ({e}); expected a box such as {{\"type\": \"closed\", \"Vb\": 0.012}}"
        ))
    })?;
    let e = if v.get("type").is_some() {
        &v
    } else if let Some(e) = v.get("enclosure") {
        e
    } else if let Some(e) = v.get("world").and_then(|w| w.get("enclosure")) {
        e
    } else {
        return err(format!("{shown}: no box in it: expected an object with `type` (closed, vented or passive_radiator) and `Vb`, or one with an `enclosure` or `world.enclosure` key"));
    };
    coilscope_core::enclosure::Enclosure::from_json(e, &|k, m| IoError(format!("{shown}: key `{k}`: {m}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_wav_f32(path: &Path, ch: u16, frames: &[Vec<f32>]) {
        let spec = hound::WavSpec {
            channels: ch,
            sample_rate: 48000,
            bits_per_sample: 32,
            sample_format: hound::SampleFormat::Float,
        };
        let mut w = hound::WavWriter::create(path, spec).unwrap();
        for f in frames {
            for s in f {
                w.write_sample(*s).unwrap();
            }
        }
        w.finalize().unwrap();
    }

    #[test]
    fn recordings_round_trip_in_physical_units() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("r.wav");
        let rec =
            Recording { fs: 48000, u: vec![0.0, 1.5, -2.25], i: vec![0.1, 0.2, -0.3], x: Some(vec![1e-3, -2e-3, 0.0]) };
        write_recording(&p, &rec).unwrap();
        let back = read_recording(&p, None).unwrap();
        assert_eq!(back.fs, 48000);
        for (a, b) in back.u.iter().zip(&rec.u).chain(back.i.iter().zip(&rec.i)) {
            assert!((a - b).abs() < 1e-6 * b.abs().max(1.0));
        }
        assert_eq!(back.x.unwrap().len(), 3);
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(d.path()).unwrap().count(), 1);
    }

    #[test]
    fn integer_pcm_needs_and_uses_scale_factors() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("int.wav");
        let spec = hound::WavSpec {
            channels: 2,
            sample_rate: 44100,
            bits_per_sample: 16,
            sample_format: hound::SampleFormat::Int,
        };
        let mut w = hound::WavWriter::create(&p, spec).unwrap();
        for s in [1000i16, 200, -1000, -200] {
            w.write_sample(s).unwrap();
        }
        w.finalize().unwrap();
        let e = read_recording(&p, None).unwrap_err().to_string();
        assert!(e.contains("16-bit integer PCM needs scale factors") && e.contains("int.wav.json"), "{e}");
        std::fs::write(d.path().join("int.wav.json"), r#"{"scale": [0.001, 0.0005]}"#).unwrap();
        let r = read_recording(&p, None).unwrap();
        assert_eq!(r.u, vec![1.0, -1.0]);
        assert_eq!(r.i, vec![0.1, -0.1]);
        std::fs::write(d.path().join("int.wav.json"), r#"{"scale": [0.001, "x"]}"#).unwrap();
        let e = read_recording(&p, None).unwrap_err().to_string();
        assert!(e.contains("key `scale`: entry 2"), "{e}");
    }

    #[test]
    fn bad_wavs_get_one_clear_line() {
        let d = tempfile::tempdir().unwrap();
        let missing = d.path().join("missing.wav");
        assert!(read_recording(&missing, None).unwrap_err().0.ends_with("missing.wav: no such file"));
        let text = d.path().join("text.wav");
        std::fs::write(&text, "hello, not audio").unwrap();
        assert!(read_recording(&text, None).unwrap_err().0.contains("text.wav: not a readable WAV file"));
        let mono = d.path().join("mono.wav");
        write_wav_f32(&mono, 1, &[vec![0.1], vec![0.2]]);
        assert!(read_recording(&mono, None).unwrap_err().0.contains("1 channel; a recording needs voltage"));
        let nan = d.path().join("nan.wav");
        write_wav_f32(&nan, 2, &[vec![0.1, 0.0], vec![0.2, f32::NAN]]);
        let e = read_recording(&nan, None).unwrap_err().0;
        assert!(e.contains("current (channel 2) sample 1") && e.contains("NaN"), "{e}");
        let empty = d.path().join("empty.wav");
        write_wav_f32(&empty, 2, &[]);
        assert!(read_recording(&empty, None).unwrap_err().0.contains("no samples"));
        let five = d.path().join("five.wav");
        write_wav_f32(&five, 5, &[vec![0.0; 5]]);
        assert!(read_recording(&five, None).unwrap_err().0.contains("5 channels; expected 1 to 3"));
        // Truncated file: cut a valid file in the middle of its data.
        let good = d.path().join("good.wav");
        write_wav_f32(&good, 2, &vec![vec![0.5, 0.25]; 100]);
        let bytes = std::fs::read(&good).unwrap();
        let cut = d.path().join("cut.wav");
        std::fs::write(&cut, &bytes[..bytes.len() - 203]).unwrap();
        let e = read_recording(&cut, None).unwrap_err().0;
        assert!(e.starts_with(&format!("{}: ", cut.display())), "{e}");
    }

    #[test]
    fn parameters_load_by_name_or_file_with_clear_errors() {
        assert_eq!(load_parameters("ptt4.0w04-01a").unwrap().re, 3.92);
        let e = load_parameters("no-such-driver").unwrap_err().0;
        assert!(e.contains("neither an embedded driver (sb17cac35-4, ptt4.0w04-01a, 18wu-4741t-00)"), "{e}");
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("p.json");
        std::fs::write(&f, r#"{"Re": 3.0, "Le": 0.5, "Bl": 5.0, "Kms": 600.0, "Mms": 0.01, "Rms": 0.5}"#).unwrap();
        let e = load_parameters(f.to_str().unwrap()).unwrap_err().0;
        assert!(e.contains("p.json: key `Le`") && e.contains("millihenry"), "{e}");
    }

    /// Threads of one process writing one file at once (a run's result beside an export of
    /// it): each write is whole, the file ends as one of them, and no temporary file is left.
    /// With one temporary name per process (`.NAME.tmp-PID`) two writers truncated each
    /// other's temporary file and the second rename failed.
    #[test]
    fn concurrent_writes_of_one_file_in_one_process_are_each_whole() {
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("result.json");
        let texts: Vec<Vec<u8>> = (0..8u8).map(|k| vec![b'a' + k; 200_000]).collect();
        for _ in 0..20 {
            std::thread::scope(|scope| {
                for t in &texts {
                    let path = &path;
                    scope.spawn(move || atomic_write(path, t).unwrap());
                }
            });
            let got = std::fs::read(&path).unwrap();
            assert!(
                texts.contains(&got),
                "the file mixes writes: {} bytes, starting {:?}",
                got.len(),
                &got[..4.min(got.len())]
            );
        }
        let names: Vec<String> = std::fs::read_dir(d.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["result.json"], "temporary files left behind");
    }

    /// A written file gets the permissions a plain create gives (0666 less the umask), not a
    /// temporary file's owner-only ones: the report and results are for others to read too.
    #[test]
    fn a_written_file_has_a_plain_files_permissions() {
        use std::os::unix::fs::PermissionsExt;
        let d = tempfile::tempdir().unwrap();
        let (plain, written) = (d.path().join("plain"), d.path().join("written"));
        std::fs::File::create(&plain).unwrap();
        atomic_write(&written, b"x").unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&written), mode(&plain));
    }

    #[test]
    fn atomic_write_refuses_missing_directories() {
        let e = atomic_write(Path::new("/nonexistent-dir-xyz/out.json"), b"{}").unwrap_err().0;
        assert!(e.contains("does not exist"), "{e}");
    }

    #[test]
    fn writes_go_through_symlinks_and_never_replace_special_files() {
        use std::os::unix::fs::FileTypeExt;
        let d = tempfile::tempdir().unwrap();
        let real = d.path().join("real.json");
        std::fs::write(&real, "old").unwrap();
        let link = d.path().join("link.json");
        std::os::unix::fs::symlink("real.json", &link).unwrap();
        atomic_write(&link, b"new").unwrap();
        assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink(), "the link was replaced");
        assert_eq!(std::fs::read_to_string(&real).unwrap(), "new");
        // A character device is written straight, and stays a device.
        atomic_write(Path::new("/dev/null"), b"discarded").unwrap();
        assert!(std::fs::metadata("/dev/null").unwrap().file_type().is_char_device());
        // A directory is refused by name.
        let e = atomic_write(d.path(), b"x").unwrap_err().to_string();
        assert!(e.contains("is a directory"), "{e}");
    }

    #[test]
    fn a_device_is_written_but_no_regular_file_appears_among_the_devices() {
        let null = Path::new("/dev/null");
        assert!(check_writable(null).is_ok());
        assert_eq!(check_outputs(null, &[PathBuf::from("/dev/null.zma")]), Ok(false), "nothing goes beside a device");
        for p in ["/dev/null.zma", "/dev/coilscope-result.json"] {
            let e = check_writable(Path::new(p)).unwrap_err().0;
            assert!(e.contains("the devices' directory") && e.contains(p), "{e}");
            assert!(atomic_write(Path::new(p), b"x").is_err(), "{p} was written");
        }
        let d = tempfile::tempdir().unwrap();
        let file = d.path().join("result.json");
        assert!(check_writable(&file).is_ok() && !file.exists(), "a check writes nothing");
        assert_eq!(check_outputs(&file, &[file.with_extension("zma")]), Ok(true));
        let e = check_outputs(&file, &[PathBuf::from("/nonexistent-dir-xyz/result.zma")]).unwrap_err().0;
        assert!(e.contains("does not exist"), "{e}");
        assert!(check_writable(Path::new("/nonexistent-dir-xyz/out.json")).unwrap_err().0.contains("does not exist"));
    }
}

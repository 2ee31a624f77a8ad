//! What a scene may make the node read. From the command line, whatever its user can read
//! (their terminal, their files). From the wire (a parameter set, `load_scene`), only
//! files inside the allowed directories once `..` and symlinks are resolved, and only
//! regular files (folders for a DICOM series) of bounded size; a refusal never says
//! whether a path outside exists.

use std::io::Read;
use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};

use super::{Scene, SceneError};

/// The most bytes a scene file or a scene sent as text may hold (the default scene is
/// about 3 KB).
pub const MAX_SCENE_BYTES: u64 = 1 << 20;

/// The parameter listing the allowed directories.
pub const ALLOWED_DIRS_PARAMETER: &str = "files.allowed_dirs";

/// What a path must name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Expect {
    File,
    /// A file or a folder (a DICOM series).
    FileOrFolder,
}

/// The file a parameter's value names, if it names one, and what it must be: `phantom`
/// and the DPCM presets' names name none.
pub fn named_file(parameter: &str, value: &str) -> Option<Expect> {
    match parameter {
        "scene_file" if !value.is_empty() => Some(Expect::File),
        "volume" if value != "phantom" => Some(Expect::FileOrFolder),
        "mesh.path" => Some(Expect::File),
        "dpcm.preset" if value.ends_with(".yaml") || value.ends_with(".yml") => Some(Expect::File),
        _ => None,
    }
}

impl Scene {
    /// Every file the scene names, by parameter name.
    pub fn named_files(&self) -> Vec<(&'static str, String)> {
        let mut named = vec![("volume", self.volume.clone()), ("dpcm.preset", self.dpcm.preset.clone())];
        if let super::MeshSource::File { path, .. } = &self.mesh {
            named.push(("mesh.path", path.display().to_string()));
        }
        named.retain(|(parameter, value)| named_file(parameter, value).is_some());
        named
    }

    /// The files the scene names by relative paths taken as relative to `dir`.
    pub(super) fn resolve_against(&mut self, dir: &Path) {
        let beside = |file: &str| dir.join(file).display().to_string();
        if named_file("volume", &self.volume).is_some() && Path::new(&self.volume).is_relative() {
            self.volume = beside(&self.volume);
        }
        if named_file("dpcm.preset", &self.dpcm.preset).is_some() && Path::new(&self.dpcm.preset).is_relative() {
            self.dpcm.preset = beside(&self.dpcm.preset);
        }
        if let super::MeshSource::File { path, .. } = &mut self.mesh {
            if path.is_relative() {
                *path = dir.join(&*path);
            }
        }
    }
}

/// The directories files named from the wire must lie in, resolved.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct AllowedDirs {
    dirs: Vec<PathBuf>,
}

impl AllowedDirs {
    /// `dirs` as they resolve now; one that does not exist is left out, and logged.
    pub fn new(dirs: impl IntoIterator<Item = PathBuf>) -> Self {
        let dirs = dirs
            .into_iter()
            .filter_map(|dir| match std::fs::canonicalize(&dir) {
                Ok(resolved) if resolved.is_dir() => Some(resolved),
                _ => {
                    tracing::warn!("{ALLOWED_DIRS_PARAMETER}: {} is not a folder here; left out", dir.display());
                    None
                }
            })
            .collect();
        Self { dirs }
    }

    /// The default: the folder of the scene the node started with and the package's
    /// `config/` (installed under `share/defvol/`, else this source tree's).
    pub fn default_dirs(scene_file: Option<&Path>) -> Vec<PathBuf> {
        let scene_dir = scene_file.map(|file| match file.parent() {
            Some(parent) if !parent.as_os_str().is_empty() => parent.to_owned(),
            _ => PathBuf::from("."),
        });
        let installed = std::env::var_os("AMENT_PREFIX_PATH")
            .map(|prefixes| std::env::split_paths(&prefixes).map(|p| p.join("share/defvol/config")).collect::<Vec<_>>())
            .unwrap_or_default();
        let source = Path::new(env!("CARGO_MANIFEST_DIR")).join("config");
        let config = installed.into_iter().chain([source]).find(|dir| dir.is_dir());
        scene_dir.into_iter().chain(config).collect()
    }

    pub fn dirs(&self) -> &[PathBuf] {
        &self.dirs
    }

    /// `path` resolved, when it lies inside an allowed directory and is what `expect` asks.
    pub fn admit(&self, path: &Path, expect: Expect) -> Result<PathBuf, String> {
        let outside = || format!("{}: outside the allowed directories ({ALLOWED_DIRS_PARAMETER})", path.display());
        let resolved = match std::fs::canonicalize(path) {
            Ok(resolved) => resolved,
            // Where a missing path would lie is where its deepest existing folder lies.
            Err(_) => match deepest_existing(path) {
                Some(folder) if self.contains(&folder) => {
                    return Err(format!("{}: no such file in the allowed directories", path.display()))
                }
                _ => return Err(outside()),
            },
        };
        if !self.contains(&resolved) {
            return Err(outside());
        }
        kind_refusal(&resolved, expect).map_or(Ok(resolved), |why| Err(format!("{}: {why}", path.display())))
    }

    fn contains(&self, resolved: &Path) -> bool {
        self.dirs.iter().any(|dir| resolved.starts_with(dir))
    }
}

/// The deepest folder above `path` that exists, resolved.
fn deepest_existing(path: &Path) -> Option<PathBuf> {
    let absolute = std::env::current_dir().ok()?.join(path);
    absolute.ancestors().skip(1).find_map(|folder| std::fs::canonicalize(folder).ok())
}

/// Why `path` is not what `expect` asks, looked at without opening it (a FIFO would block,
/// a device never end).
fn kind_refusal(path: &Path, expect: Expect) -> Option<String> {
    let kind = match std::fs::metadata(path) {
        Ok(metadata) => metadata.file_type(),
        Err(e) => return Some(e.to_string()),
    };
    let what = match () {
        _ if kind.is_file() => return None,
        _ if kind.is_dir() && expect == Expect::FileOrFolder => return None,
        _ if kind.is_dir() => "a folder",
        _ if kind.is_fifo() => "a FIFO",
        _ if kind.is_char_device() || kind.is_block_device() => "a device",
        _ if kind.is_socket() => "a socket",
        _ => "not a plain file",
    };
    Some(format!("unsupported: {what}, where a regular file is expected"))
}

/// A scene file's text, refused before reading when it is no regular file or larger than
/// [`MAX_SCENE_BYTES`].
pub fn read_scene_text(path: &Path) -> Result<String, SceneError> {
    let refused = |why: String| SceneError::Refused { path: path.display().to_string(), why };
    if let Some(why) = kind_refusal(path, Expect::File) {
        return Err(refused(why));
    }
    let mut text = String::new();
    let file = std::fs::File::open(path).map_err(|e| refused(e.to_string()))?;
    // Read one byte past the limit: a file that grew since its size was looked at is caught.
    file.take(MAX_SCENE_BYTES + 1).read_to_string(&mut text).map_err(|e| refused(e.to_string()))?;
    check_scene_size(text.len()).map_err(refused)?;
    Ok(text)
}

/// Refuses a scene larger than [`MAX_SCENE_BYTES`].
pub fn check_scene_size(bytes: usize) -> Result<(), String> {
    match bytes as u64 > MAX_SCENE_BYTES {
        true => Err(format!("unsupported: a scene of more than {MAX_SCENE_BYTES} bytes")),
        false => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An allowed folder with a scene in it, a secret outside it, and the ways out of one.
    struct Layout {
        _root: tempfile::TempDir,
        allowed: PathBuf,
        secret: PathBuf,
    }

    fn layout() -> Layout {
        let root = tempfile::tempdir().unwrap();
        let allowed = root.path().join("allowed");
        let outside = root.path().join("outside");
        for dir in [&allowed, &outside] {
            std::fs::create_dir(dir).unwrap();
        }
        std::fs::write(allowed.join("scene.yaml"), super::super::DEFAULT_SCENE).unwrap();
        let secret = outside.join("secret");
        std::fs::write(&secret, "s3cr3t\n").unwrap();
        std::os::unix::fs::symlink(&secret, allowed.join("link")).unwrap();
        std::os::unix::fs::symlink(&outside, allowed.join("door")).unwrap();
        Layout { allowed, secret, _root: root }
    }

    #[test]
    fn only_what_resolves_inside_is_admitted() {
        let l = layout();
        let dirs = AllowedDirs::new([l.allowed.clone()]);
        let scene = l.allowed.join("scene.yaml");
        assert_eq!(dirs.admit(&scene, Expect::File).unwrap(), std::fs::canonicalize(&scene).unwrap());
        let up = l.allowed.join("../outside/secret");
        let outside = [l.secret.clone(), up, l.allowed.join("link"), l.allowed.join("door/secret")];
        for path in outside {
            let why = dirs.admit(&path, Expect::File).unwrap_err();
            assert_eq!(why, format!("{}: outside the allowed directories (files.allowed_dirs)", path.display()));
        }
        // A missing path outside says the same as one that exists: no oracle for what exists.
        for missing in [l.secret.with_file_name("nothing"), l.allowed.join("door/nothing"), "/nonexistent/x".into()] {
            assert!(dirs
                .admit(&missing, Expect::File)
                .unwrap_err()
                .ends_with("outside the allowed directories (files.allowed_dirs)"));
        }
        let why = dirs.admit(&l.allowed.join("nothing.yaml"), Expect::File).unwrap_err();
        assert!(why.ends_with("no such file in the allowed directories"), "{why}");
        assert!(AllowedDirs::new([l.allowed.join("no_such_folder")]).dirs().is_empty());
    }

    #[test]
    fn folders_fifos_and_devices_are_refused_before_reading() {
        let l = layout();
        let fifo = l.allowed.join("fifo");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let dirs = AllowedDirs::new([l.allowed.clone(), "/dev".into()]);
        let cases = [(&fifo, "a FIFO"), (&l.allowed, "a folder"), (&PathBuf::from("/dev/zero"), "a device")];
        for (path, what) in cases {
            let why = dirs.admit(path, Expect::File).unwrap_err();
            assert_eq!(why, format!("{}: unsupported: {what}, where a regular file is expected", path.display()));
            let why = read_scene_text(path).unwrap_err().to_string();
            assert!(why.contains(&format!("unsupported: {what}")), "{why}");
        }
        assert!(dirs.admit(&l.allowed, Expect::FileOrFolder).is_ok(), "a DICOM series is a folder");
        let big = l.allowed.join("big.yaml");
        std::fs::write(&big, "#".repeat(MAX_SCENE_BYTES as usize + 1)).unwrap();
        let why = read_scene_text(&big).unwrap_err().to_string();
        assert!(why.ends_with(&format!("unsupported: a scene of more than {MAX_SCENE_BYTES} bytes")), "{why}");
    }

    #[test]
    fn the_files_a_scene_names_are_its_volume_mesh_and_dpcm_file() {
        let mut scene = Scene::default_scene().unwrap();
        assert!(scene.named_files().is_empty(), "the phantom, a lattice and a preset name no file");
        scene.volume = "ct.nii.gz".into();
        scene.mesh = super::super::MeshSource::File { path: "organ.vtu".into(), scale: None };
        scene.dpcm.preset = "surface.yaml".into();
        let expected = [("volume", "ct.nii.gz"), ("dpcm.preset", "surface.yaml"), ("mesh.path", "organ.vtu")];
        assert_eq!(scene.named_files(), expected.map(|(p, v)| (p, v.to_owned())));
    }
}

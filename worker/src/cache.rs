//! Scenes by content hash, and tracers by (scene, frame, settings), so that a scene
//! crosses the network once per worker, is parsed once, and each of its frames is
//! prepared once per job.
//!
//! A scene is kept as the file describes it (an [`AnimatedScene`]): an animation's
//! frames are computed here, from the one text received, not sent one by one. The
//! tracers of one scene are bounded: a sequence of frame jobs keeps the same scene for
//! as long as it runs, so without a bound every frame's tracer (a copy of the scene and
//! its hierarchy) would stay until the last frame is done.
//!
//! Reading a scene and building a frame's tracer are left to the first tile that needs
//! them ([`Prepared::get`], on the rendering pool), never done on the connection's task:
//! a mesh of millions of triangles takes seconds to read and build, and a worker that
//! sent no heartbeat for that long was dropped by the coordinator (its tiles taken
//! back, its files fetched again once it came back).

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

use protocol::{AssetRef, SceneHash, Settings};
use render::adaptive::Footprints;
use render::{AnimatedScene, Tracer};

/// A scene as received: parsed, or why it could not be used.
type Loaded = Result<Arc<AnimatedScene>, String>;

/// A scene received: its text and files until it is read, on first use (then let go:
/// a mesh file's bytes are not kept beside its geometry).
struct Received {
    unread: Mutex<Option<(String, render::MeshFiles)>>,
    loaded: OnceLock<Loaded>,
}

impl Received {
    fn get(&self) -> Loaded {
        self.loaded
            .get_or_init(|| {
                let unread = self
                    .unread
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .take();
                let (text, files) = unread.ok_or("the scene was not kept")?;
                render::parse_animated_with(&text, &files)
                    .map(Arc::new)
                    .map_err(|e| format!("the scene does not load: {e}"))
            })
            .clone()
    }
}

/// A frame's tracer, prepared once by the first tile that asks for it; the tiles asking
/// meanwhile wait for it.
pub struct Prepared {
    scene: Arc<Received>,
    frame: u32,
    settings: Settings,
    tracer: OnceLock<Result<Arc<Tracer>, String>>,
}

impl Prepared {
    /// The tracer: the scene read (if no frame of it was prepared before) and the
    /// frame's tracer built, on a thread of their own so that the hierarchy's build
    /// runs on every core as it did on the connection's task, not on the one rendering
    /// thread that waits for it. A frame the scene does not have is the loader's
    /// one-line message ("frame 122 is beyond the scene's 121 frames").
    pub fn get(&self) -> Result<Arc<Tracer>, String> {
        self.tracer
            .get_or_init(|| {
                // Named, so that neither it nor the threads it starts (Linux names a
                // thread after the one that starts it) pass for rendering threads.
                std::thread::scope(|s| {
                    match std::thread::Builder::new()
                        .name("prepare".into())
                        .spawn_scoped(s, || self.prepare())
                    {
                        Ok(thread) => thread
                            .join()
                            .unwrap_or_else(|_| Err("preparing the frame failed".to_string())),
                        Err(_) => self.prepare(),
                    }
                })
            })
            .clone()
    }

    fn prepare(&self) -> Result<Arc<Tracer>, String> {
        let scene = self.scene.get()?;
        let frame = scene
            .frame(u64::from(self.frame))
            .map_err(|e| e.to_string())?;
        Ok(Arc::new(verify::tracer(&frame, &self.settings)?))
    }
}

/// What a tracer is for: a scene's frame at given settings.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TracerKey {
    pub scene: SceneHash,
    /// From 1.
    pub frame: u32,
    pub settings: Settings,
}

/// The most tracers kept per scene: those of the frames (and settings) most recently
/// used. As many as a sequence job renders frames at once; an older one is prepared
/// again if a tile of it comes back (a retried tile), which changes no pixel.
pub const TRACERS_PER_SCENE: usize = protocol::MAX_ACTIVE_FRAMES;

#[derive(Default)]
pub struct SceneCache {
    /// Each scene received, or why it cannot be used.
    scenes: HashMap<SceneHash, Result<Arc<Received>, String>>,
    /// Each tracer with when it was last used (a count of uses, for the bound).
    tracers: HashMap<TracerKey, (Arc<Prepared>, u64)>,
    /// The adaptive footprints of each kept tracer: computed once per job, not once
    /// per tile.
    footprints: HashMap<TracerKey, Arc<Footprints>>,
    uses: u64,
}

impl SceneCache {
    /// Stores a scene sent by the coordinator, to be read with the files it names
    /// (`files`, bound to `assets`) by its first tile, checking now that it matches its
    /// hash.
    pub fn insert(
        &mut self,
        hash: SceneHash,
        text: &str,
        assets: &[AssetRef],
        files: &render::MeshFiles,
    ) {
        let received = if protocol::scene_hash(text, assets) != hash {
            Err("the scene received does not match its hash".to_string())
        } else {
            Ok(Arc::new(Received {
                unread: Mutex::new(Some((text.to_owned(), files.clone()))),
                loaded: OnceLock::new(),
            }))
        };
        self.scenes.insert(hash, received);
    }

    /// A scene that cannot be used (a file it names could not be had): its tiles fail
    /// with `reason`.
    pub fn insert_failed(&mut self, hash: SceneHash, reason: String) {
        self.scenes.insert(hash, Err(reason));
    }

    pub fn forget(&mut self, hash: &SceneHash) {
        self.scenes.remove(hash);
        self.tracers.retain(|k, _| k.scene != *hash);
        self.footprints.retain(|k, _| k.scene != *hash);
    }

    /// The footprints of a frame, computed by the first tile that needs them (on the
    /// rendering pool) and shared by the job's later tiles.
    pub fn footprints(&self, key: &TracerKey) -> Option<Arc<Footprints>> {
        self.footprints.get(key).cloned()
    }

    /// Keeps footprints computed on the pool, as long as their tracer is kept.
    pub fn keep_footprints(&mut self, key: TracerKey, f: Arc<Footprints>) {
        if self.tracers.contains_key(&key) {
            self.footprints.insert(key, f);
        }
    }

    /// The tracer for a frame of a scene at given settings, to be prepared by the first
    /// tile that uses it ([`Prepared::get`]).
    pub fn tracer(&mut self, key: TracerKey) -> Result<Arc<Prepared>, String> {
        self.uses += 1;
        let now = self.uses;
        if let Some((t, used)) = self.tracers.get_mut(&key) {
            *used = now;
            return Ok(Arc::clone(t));
        }
        let scene = match self.scenes.get(&key.scene) {
            Some(Ok(scene)) => Arc::clone(scene),
            Some(Err(e)) => return Err(e.clone()),
            None => {
                return Err(
                    "the coordinator sent a tile of a scene this worker does not have".into(),
                )
            }
        };
        let tracer = Arc::new(Prepared {
            scene,
            frame: key.frame,
            settings: key.settings,
            tracer: OnceLock::new(),
        });
        self.tracers.insert(key, (Arc::clone(&tracer), now));
        self.bound(&key.scene);
        Ok(tracer)
    }

    /// Drops the least recently used tracers of a scene (and their footprints) beyond
    /// [`TRACERS_PER_SCENE`]. Tiles already given a tracer keep theirs alive.
    fn bound(&mut self, scene: &SceneHash) {
        loop {
            let of_scene = self.tracers.iter().filter(|(k, _)| k.scene == *scene);
            if of_scene.clone().count() <= TRACERS_PER_SCENE {
                return;
            }
            let Some(oldest) = of_scene.min_by_key(|(_, (_, used))| *used).map(|(k, _)| *k) else {
                return;
            };
            self.tracers.remove(&oldest);
            self.footprints.remove(&oldest);
        }
    }

    /// How many tracers are kept (for tests).
    #[cfg(test)]
    fn tracers_kept(&self) -> usize {
        self.tracers.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::{Sampling, TileRect};

    const ORBIT: &str = include_str!("../../scenes/seed-orbit.json");

    fn settings() -> Settings {
        Settings {
            width: 48,
            height: 36,
            aa: 2,
            max_depth: 5,
            sampling: Sampling::Grid,
        }
    }

    fn loaded() -> (SceneCache, SceneHash) {
        let hash = protocol::scene_hash(ORBIT, &[]);
        let mut cache = SceneCache::default();
        cache.insert(hash, ORBIT, &[], &render::MeshFiles::none());
        (cache, hash)
    }

    fn key(scene: SceneHash, frame: u32) -> TracerKey {
        TracerKey {
            scene,
            frame,
            settings: settings(),
        }
    }

    /// The whole frame, rendered as one tile.
    fn pixels(tracer: &Tracer) -> Vec<u8> {
        let s = settings();
        let rect = TileRect {
            x: 0,
            y: 0,
            width: s.width,
            height: s.height,
        };
        render::render_tile(tracer, verify::render_rect(rect))
            .unwrap()
            .rgb
    }

    #[test]
    fn a_tile_of_frame_k_is_frame_k_of_the_animation() {
        let (mut cache, hash) = loaded();
        let animated = render::parse_animated(ORBIT).unwrap();
        let reference = |k: u64| {
            let scene = animated.frame(k).unwrap();
            pixels(&verify::tracer(&scene, &settings()).unwrap())
        };
        let frame_1 = reference(1);
        let frame_17 = reference(17);
        assert_ne!(
            frame_1, frame_17,
            "the camera moves between frames 1 and 17"
        );
        assert_eq!(
            pixels(&cache.tracer(key(hash, 17)).unwrap().get().unwrap()),
            frame_17
        );
        assert_eq!(
            pixels(&cache.tracer(key(hash, 1)).unwrap().get().unwrap()),
            frame_1
        );
        // A static scene's frame 1 is what parse_scene gives, as before frames existed.
        let still = render::parse_scene(ORBIT).unwrap();
        assert_eq!(
            pixels(&verify::tracer(&still, &settings()).unwrap()),
            frame_1
        );
    }

    #[test]
    fn a_frame_the_scene_does_not_have_fails_in_one_line() {
        let (mut cache, hash) = loaded();
        assert_eq!(
            cache.tracer(key(hash, 122)).unwrap().get().err().unwrap(),
            "frame 122 is beyond the scene's 121 frames"
        );
        assert_eq!(
            cache.tracer(key(hash, 0)).unwrap().get().err().unwrap(),
            "frame 0: frames are numbered from 1"
        );
        assert!(cache.tracer(key(hash, 121)).unwrap().get().is_ok());
        let text = r#"{"lights": [], "objects": []}"#;
        let still = protocol::scene_hash(text, &[]);
        cache.insert(still, text, &[], &render::MeshFiles::none());
        assert_eq!(
            cache.tracer(key(still, 2)).unwrap().get().err().unwrap(),
            "frame 2: the scene has no animation, only frame 1"
        );
        assert!(cache.tracer(key(still, 1)).unwrap().get().is_ok());
    }

    #[test]
    fn the_tracers_of_a_scene_are_bounded_to_the_frames_last_used() {
        let (mut cache, hash) = loaded();
        let first = cache.tracer(key(hash, 1)).unwrap();
        for k in 2..=TRACERS_PER_SCENE as u32 {
            cache.tracer(key(hash, k)).unwrap();
        }
        // Frame 1 used again: it is now the most recent, and stays.
        assert!(Arc::ptr_eq(&first, &cache.tracer(key(hash, 1)).unwrap()));
        let second = cache.tracer(key(hash, 2)).unwrap();
        for k in 10..20 {
            cache.tracer(key(hash, k)).unwrap();
            cache.tracer(key(hash, 1)).unwrap();
            assert!(cache.tracers_kept() <= TRACERS_PER_SCENE);
        }
        assert!(Arc::ptr_eq(&first, &cache.tracer(key(hash, 1)).unwrap()));
        // Frame 2 was dropped long ago: it is prepared again, the same pixels.
        let again = cache.tracer(key(hash, 2)).unwrap();
        assert!(!Arc::ptr_eq(&second, &again));
        assert_eq!(
            pixels(&second.get().unwrap()),
            pixels(&again.get().unwrap())
        );
        cache.forget(&hash);
        assert_eq!(cache.tracers_kept(), 0);
    }
}

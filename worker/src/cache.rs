//! Scenes by content hash, and tracers by (scene, settings), so that a scene crosses the
//! network once per worker and is parsed and prepared once per job.

use std::collections::HashMap;
use std::sync::Arc;

use protocol::{SceneHash, Settings};
use render::progressive::Footprints;
use render::{Scene, Tracer};
use sha2::{Digest, Sha256};

/// A scene as received: parsed, or why it could not be used.
type Loaded = Result<Arc<Scene>, String>;

#[derive(Default)]
pub struct SceneCache {
    scenes: HashMap<SceneHash, Loaded>,
    tracers: HashMap<(SceneHash, Settings), Arc<Tracer>>,
    /// The adaptive footprints of each (scene, settings): computed once per job, not
    /// once per tile.
    footprints: HashMap<(SceneHash, Settings), Arc<Footprints>>,
}

impl SceneCache {
    /// Stores a scene sent by the coordinator, checking that it matches its hash.
    pub fn insert(&mut self, hash: SceneHash, text: String) {
        let actual: SceneHash = Sha256::digest(text.as_bytes()).into();
        let loaded = if actual != hash {
            Err("the scene received does not match its hash".to_string())
        } else {
            render::parse_scene(&text)
                .map(Arc::new)
                .map_err(|e| format!("the scene does not load: {e}"))
        };
        self.scenes.insert(hash, loaded);
    }

    pub fn forget(&mut self, hash: &SceneHash) {
        self.scenes.remove(hash);
        self.tracers.retain(|(h, _), _| h != hash);
        self.footprints.retain(|(h, _), _| h != hash);
    }

    /// The footprints of a frame, computed by the first tile that needs them (on the
    /// rendering pool) and shared by the job's later tiles.
    pub fn footprints(&self, hash: &SceneHash, settings: Settings) -> Option<Arc<Footprints>> {
        self.footprints.get(&(*hash, settings)).cloned()
    }

    pub fn keep_footprints(&mut self, hash: SceneHash, settings: Settings, f: Arc<Footprints>) {
        self.footprints.insert((hash, settings), f);
    }

    /// The tracer for a scene at given settings, prepared on first use.
    pub fn tracer(&mut self, hash: &SceneHash, settings: Settings) -> Result<Arc<Tracer>, String> {
        if let Some(t) = self.tracers.get(&(*hash, settings)) {
            return Ok(Arc::clone(t));
        }
        let scene = match self.scenes.get(hash) {
            Some(Ok(scene)) => Arc::clone(scene),
            Some(Err(e)) => return Err(e.clone()),
            None => {
                return Err(
                    "the coordinator sent a tile of a scene this worker does not have".into(),
                )
            }
        };
        let tracer = Arc::new(verify::tracer(&scene, &settings)?);
        self.tracers.insert((*hash, settings), Arc::clone(&tracer));
        Ok(tracer)
    }
}

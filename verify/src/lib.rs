//! Checks of rendered pixels, shared by the worker and the coordinator.
//!
//! A pixel is a pure function of the scene, the settings and its coordinates. So the
//! coordinator can tell a right result from a wrong one by rendering a few of its
//! pixels itself ([`spot`]), and a worker's build can be told apart from the
//! coordinator's by one small render of a fixed scene ([`canary`]): identical bytes
//! mean the two renderers agree, whatever their version numbers say.

pub mod adaptive;
pub mod canary;
pub mod spot;

use protocol::{Sampling, Settings, TileRect};
use render::{Rect, RenderSettings, Scene, Tracer};

/// The renderer's settings for a job's settings on the wire.
pub fn render_settings(s: &Settings) -> RenderSettings {
    RenderSettings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling: render_sampling(s.sampling),
    }
}

/// The renderer's sampler for a sampler on the wire.
pub fn render_sampling(s: Sampling) -> render::Sampling {
    match s {
        Sampling::Grid => render::Sampling::Grid,
        Sampling::Jittered => render::Sampling::Jittered,
        Sampling::Adaptive { target_milli } => render::Sampling::Adaptive { target_milli },
    }
}

/// The renderer's rectangle for a tile on the wire.
pub fn render_rect(r: TileRect) -> Rect {
    Rect {
        x: r.x,
        y: r.y,
        width: r.width,
        height: r.height,
    }
}

/// A tracer for the scene at the job's settings, once the settings are checked.
pub fn tracer(scene: &Scene, settings: &Settings) -> Result<Tracer, String> {
    let settings = render_settings(settings);
    render::validate_settings(&settings, "").map_err(|e| format!("invalid settings: {e}"))?;
    Ok(Tracer::new(scene, settings))
}

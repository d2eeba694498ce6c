//! The studio: a page that edits a scene and moves its camera while the farm renders
//! each change progressively (docs/studio.md).
//!
//! [`plan`] says which passes a view renders; [`views`] decides, as a pure state
//! machine, which interactive jobs are still wanted; [`outbox`] decides what of their
//! tiles is still worth sending to a page.

pub mod outbox;
pub mod plan;
pub mod views;

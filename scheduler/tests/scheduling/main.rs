//! The scheduler crate's tests: its decision core (the two machines joined) against
//! random histories, its tile scheduler against a model of the daemon and
//! against a plain reference implementation, its liveness with workers that talk but do
//! not render, its job lifecycle against random histories, and both driven by the farm
//! simulation at scale.

mod farm_props;
mod lifecycle_props;
mod liveness_props;
mod pools_props;
mod reference;
mod scheduler_props;
mod sim;

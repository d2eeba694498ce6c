//! The studio's views as a pure state machine: which interactive jobs belong to which
//! page, which of them an edit makes obsolete, and which pages are gone.
//!
//! A view is one open studio page. Each accepted edit starts a new *generation* of the
//! view: the jobs of its passes are submitted together (so that workers go from the
//! coarse tiles straight on to the finer ones), and every job of an older generation is
//! cancelled at once. A job admitted after its generation was superseded (the edit and
//! the next crossed) is cancelled as soon as it is known. A view whose page has not been
//! connected for [`ABANDONED_AFTER_MS`] is dropped with its jobs, so a closed tab costs
//! the farm nothing.
//!
//! A view exists only once it was opened ([`Event::Opened`]), which the coordinator
//! does for an authorised page under a name it draws at random: that name is what
//! lets a page follow the view's stream (a browser's event stream cannot carry a
//! token), so edits and streams of a view nobody opened are refused.

use std::collections::{BTreeMap, HashMap};

use protocol::JobId;

/// Milliseconds on the coordinator's clock.
pub type Millis = u64;

/// A view's name: 128 random bits drawn by the coordinator when it is opened.
pub type ViewId = String;

/// A view without a connected page for this long is dropped.
pub const ABANDONED_AFTER_MS: Millis = 30_000;

/// At most this many views at once: each may keep the whole farm busy.
pub const MAX_VIEWS: usize = 32;

/// What happened.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// An authorised page opened a new view under this (fresh, random) name.
    Opened {
        view: ViewId,
    },
    /// The page of `view` sent a scene that the loader accepted: a new generation.
    Edit {
        view: ViewId,
    },
    /// The job of `pass` of `generation` of `view` was admitted.
    Admitted {
        view: ViewId,
        generation: u64,
        pass: u32,
        job: JobId,
    },
    /// A job ended (done, failed or cancelled).
    Ended {
        job: JobId,
    },
    /// A page connected to the view's stream, or its stream closed.
    Connected {
        view: ViewId,
    },
    Disconnected {
        view: ViewId,
    },
    /// Time passed.
    Tick,
}

/// What to do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Action {
    /// Submit the passes of this generation of the view.
    Submit { view: ViewId, generation: u64 },
    /// This job's pictures are no longer wanted.
    Cancel { job: JobId },
}

/// Why an event was refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Refused {
    #[error("the farm already has {MAX_VIEWS} studio views open: close one and try again")]
    TooManyViews,
    #[error("no studio view {0:?} (closed after {ABANDONED_AFTER_MS} ms without a page): reload the page")]
    UnknownView(ViewId),
}

/// Where a job's tiles go.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Owner {
    pub view: ViewId,
    pub generation: u64,
    pub pass: u32,
}

#[derive(Debug, Default)]
struct View {
    generation: u64,
    /// The current generation's jobs, by pass.
    jobs: BTreeMap<u32, JobId>,
    pages: u32,
    /// When the last page went away (or the view was made without one).
    alone_since: Option<Millis>,
}

/// Every open view.
#[derive(Debug, Default)]
pub struct Views {
    views: HashMap<ViewId, View>,
    owners: HashMap<JobId, Owner>,
}

impl Views {
    pub fn new() -> Views {
        Views::default()
    }

    /// Feeds one event at time `now`.
    pub fn handle(&mut self, now: Millis, event: Event) -> Result<Vec<Action>, Refused> {
        let mut actions = Vec::new();
        match event {
            Event::Opened { view } => {
                if self.views.len() >= MAX_VIEWS {
                    return Err(Refused::TooManyViews);
                }
                self.views.entry(view).or_insert_with(|| View {
                    alone_since: Some(now),
                    ..View::default()
                });
            }
            Event::Edit { view } => {
                let v = self.view(&view)?;
                v.generation += 1;
                let generation = v.generation;
                let old: Vec<JobId> = std::mem::take(&mut v.jobs).into_values().collect();
                for job in old {
                    self.owners.remove(&job);
                    actions.push(Action::Cancel { job });
                }
                actions.push(Action::Submit { view, generation });
            }
            Event::Admitted {
                view,
                generation,
                pass,
                job,
            } => match self.views.get_mut(&view) {
                Some(v) if v.generation == generation => {
                    v.jobs.insert(pass, job);
                    self.owners.insert(
                        job,
                        Owner {
                            view,
                            generation,
                            pass,
                        },
                    );
                }
                _ => actions.push(Action::Cancel { job }),
            },
            Event::Ended { job } => {
                if let Some(owner) = self.owners.remove(&job) {
                    if let Some(v) = self.views.get_mut(&owner.view) {
                        v.jobs.remove(&owner.pass);
                    }
                }
            }
            Event::Connected { view } => {
                let v = self.view(&view)?;
                v.pages += 1;
                v.alone_since = None;
            }
            Event::Disconnected { view } => {
                if let Some(v) = self.views.get_mut(&view) {
                    v.pages = v.pages.saturating_sub(1);
                    if v.pages == 0 {
                        v.alone_since = Some(now);
                    }
                }
            }
            Event::Tick => {
                let gone: Vec<ViewId> = self
                    .views
                    .iter()
                    .filter(|(_, v)| {
                        v.alone_since
                            .is_some_and(|t| now.saturating_sub(t) >= ABANDONED_AFTER_MS)
                    })
                    .map(|(id, _)| id.clone())
                    .collect();
                for id in gone {
                    let v = self.views.remove(&id).expect("listed above");
                    for job in v.jobs.into_values() {
                        self.owners.remove(&job);
                        actions.push(Action::Cancel { job });
                    }
                }
            }
        }
        Ok(actions)
    }

    /// The view and pass a job renders for, if it is still wanted.
    pub fn owner(&self, job: JobId) -> Option<&Owner> {
        self.owners.get(&job)
    }

    /// The view's current generation (0 before its first edit).
    pub fn generation(&self, view: &str) -> Option<u64> {
        self.views.get(view).map(|v| v.generation)
    }

    /// When the next view may be abandoned.
    pub fn next_deadline(&self) -> Option<Millis> {
        self.views
            .values()
            .filter_map(|v| v.alone_since)
            .min()
            .map(|t| t + ABANDONED_AFTER_MS)
    }

    fn view(&mut self, id: &str) -> Result<&mut View, Refused> {
        self.views
            .get_mut(id)
            .ok_or_else(|| Refused::UnknownView(id.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn open(views: &mut Views, now: Millis, view: &str) {
        views
            .handle(now, Event::Opened { view: view.into() })
            .unwrap();
    }

    fn edit(views: &mut Views, now: Millis, view: &str) -> Vec<Action> {
        views
            .handle(now, Event::Edit { view: view.into() })
            .unwrap()
    }

    fn admit(views: &mut Views, view: &str, generation: u64, pass: u32, job: JobId) -> Vec<Action> {
        views
            .handle(
                0,
                Event::Admitted {
                    view: view.into(),
                    generation,
                    pass,
                    job,
                },
            )
            .unwrap()
    }

    #[test]
    fn an_edit_cancels_every_job_of_the_previous_generation() {
        let mut views = Views::new();
        open(&mut views, 0, "a");
        views
            .handle(0, Event::Connected { view: "a".into() })
            .unwrap();
        assert_eq!(
            edit(&mut views, 0, "a"),
            [Action::Submit {
                view: "a".into(),
                generation: 1
            }]
        );
        for (pass, job) in [(0, 10), (1, 11), (2, 12)] {
            assert!(admit(&mut views, "a", 1, pass, job).is_empty());
        }
        views.handle(0, Event::Ended { job: 10 }).unwrap();
        assert_eq!(views.owner(11).map(|o| o.pass), Some(1));
        let mut actions = edit(&mut views, 5, "a");
        actions.sort_by_key(|a| format!("{a:?}"));
        assert_eq!(
            actions,
            [
                Action::Cancel { job: 11 },
                Action::Cancel { job: 12 },
                Action::Submit {
                    view: "a".into(),
                    generation: 2
                }
            ]
        );
        assert_eq!(views.owner(11), None, "a superseded job's tiles go nowhere");
    }

    #[test]
    fn a_job_admitted_after_its_generation_was_superseded_is_cancelled() {
        let mut views = Views::new();
        open(&mut views, 0, "a");
        edit(&mut views, 0, "a");
        edit(&mut views, 1, "a");
        assert_eq!(admit(&mut views, "a", 1, 0, 7), [Action::Cancel { job: 7 }]);
        assert_eq!(views.owner(7), None);
        assert!(admit(&mut views, "a", 2, 0, 8).is_empty());
        assert_eq!(
            views.owner(8),
            Some(&Owner {
                view: "a".into(),
                generation: 2,
                pass: 0
            })
        );
        // A view that does not exist (dropped meanwhile) wants nothing either.
        assert_eq!(
            admit(&mut views, "gone", 1, 0, 9),
            [Action::Cancel { job: 9 }]
        );
    }

    #[test]
    fn a_view_left_without_a_page_is_dropped_with_its_jobs() {
        let mut views = Views::new();
        open(&mut views, 0, "a");
        views
            .handle(0, Event::Connected { view: "a".into() })
            .unwrap();
        views
            .handle(0, Event::Connected { view: "a".into() })
            .unwrap();
        edit(&mut views, 0, "a");
        admit(&mut views, "a", 1, 0, 3);
        views
            .handle(10, Event::Disconnected { view: "a".into() })
            .unwrap();
        assert_eq!(views.next_deadline(), None, "one page is still open");
        views
            .handle(20, Event::Disconnected { view: "a".into() })
            .unwrap();
        assert_eq!(views.next_deadline(), Some(20 + ABANDONED_AFTER_MS));
        let early = views
            .handle(20 + ABANDONED_AFTER_MS - 1, Event::Tick)
            .unwrap();
        assert!(early.is_empty());
        // A page that comes back in time keeps its view.
        views
            .handle(25, Event::Connected { view: "a".into() })
            .unwrap();
        assert!(views
            .handle(10 * ABANDONED_AFTER_MS, Event::Tick)
            .unwrap()
            .is_empty());
        views
            .handle(100, Event::Disconnected { view: "a".into() })
            .unwrap();
        let late = views.handle(100 + ABANDONED_AFTER_MS, Event::Tick).unwrap();
        assert_eq!(late, [Action::Cancel { job: 3 }]);
        assert_eq!(views.generation("a"), None);
        assert_eq!(views.owner(3), None);
    }

    #[test]
    fn the_number_of_views_is_bounded() {
        let mut views = Views::new();
        for i in 0..MAX_VIEWS {
            open(&mut views, 0, &format!("v{i}"));
            edit(&mut views, 0, &format!("v{i}"));
        }
        assert_eq!(
            views.handle(
                0,
                Event::Opened {
                    view: "one more".into()
                }
            ),
            Err(Refused::TooManyViews)
        );
        // The open ones go on.
        assert!(views.handle(0, Event::Edit { view: "v0".into() }).is_ok());
        // An edit without a page ever connecting is abandoned too.
        let dropped = views.handle(ABANDONED_AFTER_MS, Event::Tick).unwrap();
        assert!(dropped.is_empty());
        assert_eq!(views.generation("v0"), None);
        open(&mut views, 0, "one more");
        assert!(views
            .handle(
                0,
                Event::Edit {
                    view: "one more".into()
                }
            )
            .is_ok());
    }

    #[test]
    fn only_an_opened_view_takes_edits_and_pages() {
        let mut views = Views::new();
        let unknown = Err(Refused::UnknownView("guess".into()));
        assert_eq!(
            views.handle(
                0,
                Event::Connected {
                    view: "guess".into()
                }
            ),
            unknown
        );
        assert_eq!(
            views.handle(
                0,
                Event::Edit {
                    view: "guess".into()
                }
            ),
            unknown
        );
        assert_eq!(views.generation("guess"), None);
        open(&mut views, 0, "guess");
        assert_eq!(views.generation("guess"), Some(0));
        assert!(views
            .handle(
                0,
                Event::Connected {
                    view: "guess".into()
                }
            )
            .is_ok());
        // Opened and never connected: abandoned like a closed page.
        open(&mut views, 0, "other");
        views.handle(ABANDONED_AFTER_MS, Event::Tick).unwrap();
        assert_eq!(views.generation("other"), None);
        assert_eq!(views.generation("guess"), Some(0));
    }
}

//! Operating a farm of real `tessera` processes on 127.0.0.1: the client commands, the
//! controls of jobs and machines, worker names, what jobs report, configuration,
//! monitoring, the coordinator's pages in a real browser (the status page, the
//! studio, the previews of sequences), and the Python client's suite.

mod client_commands;
mod configuration;
mod controls;
mod event_stream;
mod http_api;
mod job_reports;
mod monitoring;
mod python_client;
mod sequence_preview;
mod status_page;
mod studio;
mod webhooks;
mod worker_names;

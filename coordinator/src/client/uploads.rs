//! A submission's files: the client asks which the coordinator lacks, uploads only
//! those (from where an upload left off: a lost connection costs at most a chunk), and
//! submits; a submission answered with files gone meanwhile (collected between the
//! upload and the submission) uploads them and submits again.

use std::io::{Read, Seek, SeekFrom};
use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use protocol::{
    AssetAnswer, AssetKey, AssetRef, AssetRequest, ClientRequest, ClientResponse, JobId, JobSpec,
    Lacking, ASSET_CHUNK,
};

use super::{unexpected, Client};

/// A file a scene names, on this machine: what the job names it (`asset`) and where
/// its bytes are.
#[derive(Clone, Debug)]
pub struct LocalFile {
    pub asset: AssetRef,
    pub path: PathBuf,
}

/// How a submission's upload goes: told when it starts, after each chunk and when it
/// ends, so that a command can show it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct UploadProgress {
    /// Files the coordinator lacks (in part or whole), and their bytes it lacks.
    pub files: usize,
    pub total: u64,
    /// Of those bytes, sent so far.
    pub sent: u64,
    /// The last of them is in.
    pub finished: bool,
}

/// How many times a submission uploads what the coordinator says it lacks before
/// giving up: files collected twice between an upload and the submission mean a
/// coordinator short of room, which another try will not fix.
const SUBMITS: usize = 3;

impl Client {
    /// Calls `report` as a submission's files are uploaded (not for files the
    /// coordinator has already).
    pub fn on_upload(&mut self, report: impl FnMut(UploadProgress) + Send + 'static) {
        self.upload_progress = Some(Box::new(report));
    }

    fn report_upload(&mut self, progress: UploadProgress) {
        if let Some(report) = &mut self.upload_progress {
            report(progress);
        }
    }

    /// Which of `keys` the coordinator lacks, and what it has received of each.
    pub async fn lacking(&mut self, keys: Vec<AssetKey>) -> Result<Vec<Lacking>> {
        match self
            .request(ClientRequest::Assets(AssetRequest::Lacking { keys }))
            .await?
        {
            ClientResponse::Assets(AssetAnswer::Lacking { lacking }) => Ok(lacking),
            other => Err(unexpected(&other)),
        }
    }

    /// Uploads the file from byte `from` (what the coordinator has of it) to its end,
    /// checking on the way that it is still the file that was hashed.
    pub async fn upload(&mut self, file: &LocalFile, from: u64) -> Result<()> {
        self.upload_counted(file, from, &mut |_| {}).await
    }

    /// [`Client::upload`], telling `sent` the bytes each chunk added.
    async fn upload_counted(
        &mut self,
        file: &LocalFile,
        from: u64,
        sent: &mut (dyn FnMut(u64) + Send),
    ) -> Result<()> {
        let key = file.asset.key;
        let shown = file.path.display();
        let mut f =
            std::fs::File::open(&file.path).with_context(|| format!("cannot read {shown}"))?;
        let size = f
            .metadata()
            .with_context(|| format!("cannot read {shown}"))?
            .len();
        if size != key.size {
            bail!(
                "{shown} changed since it was read ({size} bytes, not {})",
                key.size
            );
        }
        f.seek(SeekFrom::Start(from))
            .with_context(|| format!("cannot read {shown}"))?;
        let mut offset = from;
        loop {
            let len = (key.size - offset).min(ASSET_CHUNK as u64) as usize;
            let mut bytes = vec![0; len];
            f.read_exact(&mut bytes)
                .with_context(|| format!("cannot read {shown}"))?;
            let request = AssetRequest::Upload { key, offset, bytes };
            match self.request(ClientRequest::Assets(request)).await {
                Ok(ClientResponse::Assets(AssetAnswer::Received {
                    received, complete, ..
                })) => {
                    if complete {
                        sent(key.size.saturating_sub(offset));
                        return Ok(());
                    }
                    if received <= offset && len > 0 {
                        bail!("the coordinator took none of {shown} at byte {offset}");
                    }
                    sent(received.saturating_sub(offset));
                    offset = received;
                    f.seek(SeekFrom::Start(offset))
                        .with_context(|| format!("cannot read {shown}"))?;
                }
                Ok(other) => return Err(unexpected(&other)),
                Err(e) => return Err(e.context(format!("{shown}: cannot upload it"))),
            }
        }
    }

    /// Uploads what the coordinator lacks of `files`, each once.
    async fn upload_lacking(&mut self, files: &[LocalFile], lacking: Vec<Lacking>) -> Result<()> {
        let todo: Vec<(&LocalFile, u64)> = lacking
            .iter()
            .filter_map(|l| {
                let file = files.iter().find(|f| f.asset.key == l.key)?;
                Some((file, l.received))
            })
            .collect();
        if todo.is_empty() {
            return Ok(());
        }
        let mut progress = UploadProgress {
            files: todo.len(),
            total: todo
                .iter()
                .map(|(f, from)| f.asset.key.size.saturating_sub(*from))
                .sum(),
            sent: 0,
            finished: false,
        };
        self.report_upload(progress);
        // Told after each chunk: taken out of the client while it uploads.
        let mut report = self.upload_progress.take();
        let outcome = async {
            for (file, from) in todo {
                let mut sent = |n: u64| {
                    progress.sent += n;
                    if let Some(report) = &mut report {
                        report(progress);
                    }
                };
                self.upload_counted(file, from, &mut sent).await?;
            }
            Ok::<_, anyhow::Error>(())
        }
        .await;
        self.upload_progress = report;
        outcome?;
        progress.finished = true;
        self.report_upload(progress);
        Ok(())
    }

    /// Submits a job whose scene names `files` (`spec.assets` is set from them): the
    /// files the coordinator lacks are uploaded first, and again if the submission
    /// finds some gone.
    pub async fn submit_with_files(
        &mut self,
        mut spec: JobSpec,
        files: &[LocalFile],
    ) -> Result<JobId> {
        spec.assets = files.iter().map(|f| f.asset.clone()).collect();
        if files.is_empty() {
            return self.submit(spec).await;
        }
        let mut keys: Vec<AssetKey> = files.iter().map(|f| f.asset.key).collect();
        keys.sort_unstable();
        keys.dedup();
        let lacking = self.lacking(keys).await?;
        self.upload_lacking(files, lacking).await?;
        for _ in 0..SUBMITS {
            match self.request(ClientRequest::Submit(spec.clone())).await? {
                ClientResponse::Submitted { job } => return Ok(job),
                ClientResponse::Assets(AssetAnswer::SubmitLacking { lacking }) => {
                    let lacking = self.lacking(lacking).await?;
                    self.upload_lacking(files, lacking).await?;
                }
                other => return Err(unexpected(&other)),
            }
        }
        bail!("the coordinator kept losing the scene's files before the job was submitted")
    }
}

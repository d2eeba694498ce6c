//! Would compressing tile results pay? Real tile results of the seed job, compressed
//! with a few well-kept codecs, with and without a PNG-like filter first: ratio and
//! time per tile, then what that means on a 100 Mbit/s link.

use std::fmt::Write as _;
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use flate2::{Compress, Compression, Decompress, FlushCompress, FlushDecompress, Status};
use rayon::prelude::*;
use render::{render_tile, Rect, RenderSettings, Tracer};

use super::measure;
use super::scenes;

/// Bytes a tile result's frame adds to its pixels: the length prefix and the
/// `TileDone` fields around `rgb` (docs/protocol.md §2).
pub const TILE_ENVELOPE: u64 = 4 + 56;
/// The link of the question: 100 Mbit/s, in bytes per second.
pub const LINK_BYTES_PER_SECOND: f64 = 100e6 / 8.0;
/// Cores per worker in the question.
pub const WORKER_CORES: f64 = 2.0;

/// A codec and its level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Codec {
    Lz4,
    Deflate(u32),
    Zstd(i32),
}

impl Codec {
    pub fn name(self) -> String {
        match self {
            Codec::Lz4 => "lz4_flex".into(),
            Codec::Deflate(l) => format!("deflate {l}"),
            Codec::Zstd(l) => format!("zstd {l}"),
        }
    }
}

/// A reversible transform of a tile's rows before compression.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    None,
    /// Each byte minus the same channel of the pixel to its left (PNG's "sub").
    Sub,
    /// Each byte minus the same byte of the row above (PNG's "up").
    Up,
}

impl Filter {
    pub fn name(self) -> &'static str {
        match self {
            Filter::None => "none",
            Filter::Sub => "sub",
            Filter::Up => "up",
        }
    }

    fn apply(self, rgb: &[u8], width: usize, out: &mut Vec<u8>) {
        out.clear();
        out.extend_from_slice(rgb);
        let row = width * 3;
        match self {
            Filter::None => {}
            Filter::Sub => {
                for line in out.chunks_mut(row) {
                    for i in (3..line.len()).rev() {
                        line[i] = line[i].wrapping_sub(line[i - 3]);
                    }
                }
            }
            Filter::Up => {
                for i in (row..out.len()).rev() {
                    out[i] = out[i].wrapping_sub(out[i - row]);
                }
            }
        }
    }

    fn undo(self, data: &mut [u8], width: usize) {
        let row = width * 3;
        match self {
            Filter::None => {}
            Filter::Sub => {
                for line in data.chunks_mut(row) {
                    for i in 3..line.len() {
                        line[i] = line[i].wrapping_add(line[i - 3]);
                    }
                }
            }
            Filter::Up => {
                for i in row..data.len() {
                    data[i] = data[i].wrapping_add(data[i - row]);
                }
            }
        }
    }
}

/// A codec with its contexts, reused from tile to tile as a worker and a coordinator
/// would.
enum Engine {
    Lz4,
    Deflate(Box<Compress>, Box<Decompress>),
    Zstd(
        Box<zstd::bulk::Compressor<'static>>,
        Box<zstd::bulk::Decompressor<'static>>,
    ),
}

impl Engine {
    fn new(codec: Codec) -> Result<Engine> {
        Ok(match codec {
            Codec::Lz4 => Engine::Lz4,
            Codec::Deflate(level) => Engine::Deflate(
                Box::new(Compress::new(Compression::new(level), false)),
                Box::new(Decompress::new(false)),
            ),
            Codec::Zstd(level) => Engine::Zstd(
                Box::new(zstd::bulk::Compressor::new(level)?),
                Box::new(zstd::bulk::Decompressor::new()?),
            ),
        })
    }

    fn compress(&mut self, data: &[u8], out: &mut Vec<u8>) -> Result<()> {
        out.clear();
        match self {
            Engine::Lz4 => {
                out.resize(lz4_flex::block::get_maximum_output_size(data.len()), 0);
                let n = lz4_flex::block::compress_into(data, out)?;
                out.truncate(n);
            }
            Engine::Deflate(c, _) => {
                c.reset();
                out.reserve(data.len() + data.len() / 8 + 64);
                loop {
                    let consumed = c.total_in() as usize;
                    let status = c.compress_vec(&data[consumed..], out, FlushCompress::Finish)?;
                    if status == Status::StreamEnd {
                        break;
                    }
                    out.reserve(out.capacity());
                }
            }
            Engine::Zstd(c, _) => {
                out.reserve(zstd::zstd_safe::compress_bound(data.len()));
                c.compress_to_buffer(data, out)?;
            }
        }
        Ok(())
    }

    fn decompress(&mut self, data: &[u8], raw_len: usize, out: &mut Vec<u8>) -> Result<()> {
        out.clear();
        match self {
            Engine::Lz4 => {
                out.resize(raw_len, 0);
                let n = lz4_flex::block::decompress_into(data, out)?;
                out.truncate(n);
            }
            Engine::Deflate(_, d) => {
                d.reset(false);
                out.reserve(raw_len);
                d.decompress_vec(data, out, FlushDecompress::Finish)?;
            }
            Engine::Zstd(_, d) => {
                out.reserve(raw_len);
                d.decompress_to_buffer(data, out)?;
            }
        }
        Ok(())
    }
}

/// Tile results of one job's tiling.
pub struct TileSet {
    pub side: u32,
    /// (width, pixels) of each tile.
    pub tiles: Vec<(usize, Vec<u8>)>,
}

impl TileSet {
    pub fn raw_bytes(&self) -> u64 {
        self.tiles.iter().map(|(_, t)| t.len() as u64).sum()
    }
}

/// The seed frame's tiles as the coordinator cuts them, and cut smaller.
pub struct Frames {
    pub width: u32,
    pub height: u32,
    pub aa: u32,
    pub sets: Vec<TileSet>,
    /// Mean time to render one tile of the job's own tiling on one thread.
    pub tile_render_seconds: f64,
}

/// The coordinator's default tile side (coordinator/src/tiling.rs): about 64 K samples
/// a tile, halved until the frame has at least 64 tiles.
pub fn default_tile_side(width: u32, height: u32, aa: u32) -> u32 {
    let mut side = (256 / aa.max(1)).clamp(16, 256);
    while side > 16 && width.div_ceil(side) * height.div_ceil(side) < 64 {
        side /= 2;
    }
    side
}

/// Renders the seed scene at `width` × `height`, `aa`, tile by tile with the renderer
/// the workers use, on one thread (to time a tile) and returns its tiles at the job's
/// side and at `smaller` sides cut from the same pixels (a frame has the same bytes in
/// any tiling).
pub fn render_tiles(width: u32, height: u32, aa: u32, smaller: &[u32]) -> Result<Frames> {
    let scene = render::parse_scene(&scenes::seed().json).context("the seed scene")?;
    let settings = RenderSettings {
        width,
        height,
        aa,
        ..scene.settings
    };
    let tracer = Tracer::new(&scene, settings);
    let side = default_tile_side(width, height, aa);
    let rects = render::tiles(&settings, side);
    let pool = measure::pool(1)?;
    let started = Instant::now();
    let rendered = pool.install(|| {
        rects
            .par_iter()
            .map(|r| render_tile(&tracer, *r))
            .collect::<Result<Vec<_>, _>>()
    })?;
    let tile_render_seconds = started.elapsed().as_secs_f64() / rects.len() as f64;
    let (w, h) = (width as usize, height as usize);
    let mut frame = vec![0u8; w * h * 3];
    for t in &rendered {
        let Rect {
            x,
            y,
            width: tw,
            height: th,
        } = t.rect;
        for row in 0..th as usize {
            let dst = ((y as usize + row) * w + x as usize) * 3;
            let src = row * tw as usize * 3;
            frame[dst..dst + tw as usize * 3].copy_from_slice(&t.rgb[src..src + tw as usize * 3]);
        }
    }
    let mut sets = vec![TileSet {
        side,
        tiles: rendered
            .into_iter()
            .map(|t| (t.rect.width as usize, t.rgb))
            .collect(),
    }];
    for &s in smaller {
        let tiles = render::tiles(&settings, s)
            .into_iter()
            .map(|r| {
                let mut rgb = Vec::with_capacity(r.pixel_count() as usize * 3);
                for row in r.y..r.y + r.height {
                    let start = (row as usize * w + r.x as usize) * 3;
                    rgb.extend_from_slice(&frame[start..start + r.width as usize * 3]);
                }
                (r.width as usize, rgb)
            })
            .collect();
        sets.push(TileSet { side: s, tiles });
    }
    Ok(Frames {
        width,
        height,
        aa,
        sets,
        tile_render_seconds,
    })
}

/// One codec and filter on one tile set.
pub struct Measured {
    pub side: u32,
    pub codec: Option<Codec>,
    pub filter: Filter,
    pub raw_bytes: u64,
    pub compressed_bytes: u64,
    pub tiles: usize,
    /// Per tile, on one thread, the filter included.
    pub compress_seconds: f64,
    pub decompress_seconds: f64,
}

impl Measured {
    pub fn ratio(&self) -> f64 {
        self.raw_bytes as f64 / self.compressed_bytes as f64
    }

    pub fn label(&self) -> String {
        match self.codec {
            None => "uncompressed".into(),
            Some(c) if self.filter == Filter::None => c.name(),
            Some(c) => format!("{} + {}", self.filter.name(), c.name()),
        }
    }

    /// Mean bytes of a tile result's frame.
    pub fn frame_bytes(&self) -> f64 {
        self.compressed_bytes as f64 / self.tiles as f64 + TILE_ENVELOPE as f64
    }
}

/// Runs `pass` at least twice and until `min_time` has passed; the fastest pass.
fn best_pass(min_time: Duration, mut pass: impl FnMut() -> Result<()>) -> Result<f64> {
    let started = Instant::now();
    let mut best = f64::INFINITY;
    let mut runs = 0;
    while runs < 2 || started.elapsed() < min_time {
        let t = Instant::now();
        pass()?;
        best = best.min(t.elapsed().as_secs_f64());
        runs += 1;
    }
    Ok(best)
}

/// The candidates.
pub fn codecs() -> Vec<Codec> {
    vec![
        Codec::Lz4,
        Codec::Deflate(1),
        Codec::Deflate(6),
        Codec::Zstd(-1),
        Codec::Zstd(1),
        Codec::Zstd(3),
    ]
}

/// Measures every codec with every filter on every tile set: sizes from one pass,
/// times the fastest of passes lasting at least `min_time` in all.
pub fn measure(frames: &Frames, min_time: Duration) -> Result<Vec<Measured>> {
    let mut out = Vec::new();
    for set in &frames.sets {
        let raw_bytes = set.raw_bytes();
        out.push(Measured {
            side: set.side,
            codec: None,
            filter: Filter::None,
            raw_bytes,
            compressed_bytes: raw_bytes,
            tiles: set.tiles.len(),
            compress_seconds: 0.0,
            decompress_seconds: 0.0,
        });
        for codec in codecs() {
            for filter in [Filter::None, Filter::Sub, Filter::Up] {
                let mut engine = Engine::new(codec)?;
                let mut scratch = Vec::new();
                let mut packed: Vec<Vec<u8>> = vec![Vec::new(); set.tiles.len()];
                let compress = best_pass(min_time, || {
                    for ((width, rgb), out) in set.tiles.iter().zip(packed.iter_mut()) {
                        filter.apply(rgb, *width, &mut scratch);
                        engine.compress(&scratch, out)?;
                    }
                    Ok(())
                })?;
                let compressed_bytes = packed.iter().map(|p| p.len() as u64).sum();
                let mut unpacked = Vec::new();
                for ((width, rgb), p) in set.tiles.iter().zip(&packed) {
                    engine.decompress(p, rgb.len(), &mut unpacked)?;
                    filter.undo(&mut unpacked, *width);
                    ensure!(
                        unpacked == *rgb,
                        "{} with filter {} did not give back the tile",
                        codec.name(),
                        filter.name()
                    );
                }
                let decompress = best_pass(min_time, || {
                    for ((width, rgb), p) in set.tiles.iter().zip(&packed) {
                        engine.decompress(p, rgb.len(), &mut unpacked)?;
                        filter.undo(&mut unpacked, *width);
                    }
                    Ok(())
                })?;
                let n = set.tiles.len() as f64;
                out.push(Measured {
                    side: set.side,
                    codec: Some(codec),
                    filter,
                    raw_bytes,
                    compressed_bytes,
                    tiles: set.tiles.len(),
                    compress_seconds: compress / n,
                    decompress_seconds: decompress / n,
                });
            }
        }
        eprintln!(
            "compression: {} tiles of side {} measured",
            set.tiles.len(),
            set.side
        );
    }
    Ok(out)
}

/// What a codec changes on a 100 Mbit/s link, per tile and for the farm.
pub struct Verdict {
    /// Transfer time saved per tile (seconds).
    pub saved: f64,
    /// CPU per tile, worker plus coordinator (seconds).
    pub cpu: f64,
    /// Two-core workers whose results fill the link, each rendering a tile per core
    /// every `tile_render_seconds` (plus the compression).
    pub workers_to_fill: f64,
    /// Share of one coordinator core that decompression takes with the link full.
    pub coordinator_share: f64,
}

pub fn verdict(m: &Measured, tile_render_seconds: f64) -> Verdict {
    let raw = m.raw_bytes as f64 / m.tiles as f64 + TILE_ENVELOPE as f64;
    let sent = m.frame_bytes();
    let saved = (raw - sent) / LINK_BYTES_PER_SECOND;
    let cpu = m.compress_seconds + m.decompress_seconds;
    let per_worker = WORKER_CORES * sent / (tile_render_seconds + m.compress_seconds);
    let tiles_per_second_full = LINK_BYTES_PER_SECOND / sent;
    Verdict {
        saved,
        cpu,
        workers_to_fill: LINK_BYTES_PER_SECOND / per_worker,
        coordinator_share: tiles_per_second_full * m.decompress_seconds,
    }
}

/// The compression table and its reading, in Markdown.
pub fn markdown(frames: &Frames, measured: &[Measured]) -> String {
    let mut md = String::new();
    let job_side = frames.sets.first().map_or(0, |s| s.side);
    let _ = writeln!(
        md,
        "### Compressing tile results\n\n\
         The seed scene at {}×{}, aa {}, rendered tile by tile with the workers' renderer \
         ({}-pixel tiles, the coordinator's default: {:.2} ms a tile on one thread), and \
         the same pixels cut into smaller tiles (an aa 8 job gets 32-pixel tiles of about \
         the same cost each). Times per tile on one thread, the filter included; ratio = \
         raw / compressed bytes over all tiles. \"Link full at\" is the number of 2-core \
         workers whose results fill a 100 Mbit/s link (one tile per core every {:.2} ms, \
         frame envelope of {} bytes included); \"coordinator\" is the share of one core \
         the coordinator spends decompressing with that link full.\n",
        frames.width,
        frames.height,
        frames.aa,
        job_side,
        frames.tile_render_seconds * 1e3,
        frames.tile_render_seconds * 1e3,
        TILE_ENVELOPE,
    );
    for set in &frames.sets {
        let _ = writeln!(
            md,
            "\n#### {} tiles of side {} ({:.0} bytes of pixels a tile)\n\n\
             | codec | ratio | bytes/tile | compress (µs) | decompress (µs) | transfer saved at 100 Mbit/s (µs) | CPU spent (µs) | link full at (workers) | coordinator |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|",
            set.tiles.len(),
            set.side,
            set.raw_bytes() as f64 / set.tiles.len() as f64
        );
        for m in measured.iter().filter(|m| m.side == set.side) {
            let v = verdict(m, frames.tile_render_seconds);
            let _ = writeln!(
                md,
                "| {} | {:.2} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.1} | {:.1}% |",
                m.label(),
                m.ratio(),
                m.frame_bytes(),
                m.compress_seconds * 1e6,
                m.decompress_seconds * 1e6,
                v.saved * 1e6,
                v.cpu * 1e6,
                v.workers_to_fill,
                100.0 * v.coordinator_share
            );
        }
    }
    md
}

/// The compression measurements as CSV rows.
pub fn csv(frames: &Frames, measured: &[Measured]) -> String {
    let mut csv = String::from(
        "side,codec,filter,tiles,raw_bytes,compressed_bytes,ratio,compress_us,decompress_us,saved_us_100mbit,workers_to_fill_100mbit,coordinator_share\n",
    );
    for m in measured {
        let v = verdict(m, frames.tile_render_seconds);
        let _ = writeln!(
            csv,
            "{},{},{},{},{},{},{:.4},{:.2},{:.2},{:.1},{:.2},{:.4}",
            m.side,
            m.codec.map_or_else(|| "none".into(), Codec::name),
            m.filter.name(),
            m.tiles,
            m.raw_bytes,
            m.compressed_bytes,
            m.ratio(),
            m.compress_seconds * 1e6,
            m.decompress_seconds * 1e6,
            v.saved * 1e6,
            v.workers_to_fill,
            v.coordinator_share
        );
    }
    csv
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filters_and_codecs_round_trip() {
        let width = 5;
        let rgb: Vec<u8> = (0..width * 4 * 3).map(|i| (i * 37 % 251) as u8).collect();
        for filter in [Filter::None, Filter::Sub, Filter::Up] {
            let mut f = Vec::new();
            filter.apply(&rgb, width, &mut f);
            for codec in codecs() {
                let mut e = Engine::new(codec).unwrap();
                let (mut packed, mut back) = (Vec::new(), Vec::new());
                e.compress(&f, &mut packed).unwrap();
                e.decompress(&packed, f.len(), &mut back).unwrap();
                filter.undo(&mut back, width);
                assert_eq!(back, rgb, "{codec:?} {filter:?}");
            }
        }
    }

    #[test]
    fn default_tile_side_matches_the_coordinator() {
        assert_eq!(default_tile_side(1920, 1080, 2), 128);
        assert_eq!(default_tile_side(600, 400, 1), 64);
        assert_eq!(default_tile_side(2560, 1440, 8), 32);
    }
}

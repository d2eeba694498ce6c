//! Camera rays: the grid's samples of a span of pixels, their directions (from the
//! image-plane tables when the frame is small enough), traced four at a time and handed
//! to a [`GridSink`] in sample order.

use super::prepare::SampleGroup;
use super::ray::{Packet, Path, FROM_CAMERA};
use super::{Ctx, Tracer};
use crate::simd::isa_dispatch;
use crate::vec3::{Vec3, F4, LANES, M4, V4};

/// What a grid render does with the colours it traces ([`Tracer::grid_span`]).
pub(crate) trait GridSink {
    /// The clipped colours of a pixel's next `count` samples, in lanes `0..count` of
    /// `colors` (the lanes beyond hold anything); a pixel's samples come in sample
    /// order, four at a time, as they were traced.
    fn samples(&mut self, colors: &V4, count: usize);
    /// The end of a pixel, with the sum of its samples' colours in sample order.
    fn pixel(&mut self, sum: Vec3);
}

impl Tracer {
    /// Traces the n × n grid samples (section 3) of the pixels `columns` of row `j`, left
    /// to right, and hands `sink` each sample's clipped colour in sample order, then each
    /// pixel's sum of them, summed in sample order. A whole span at a time, so that the
    /// constants of the loop are set up once and the sink's own work on each pixel is
    /// compiled with the tracer's SIMD code. Adds the rays traced to `rays`.
    pub(crate) fn grid_span<S: GridSink>(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        rays: &mut u64,
        sink: &mut S,
    ) {
        self.with_ctx(rays, |ctx| self.grid_span_isa(j, columns, ctx, sink))
    }

    isa_dispatch! {
        /// [`Tracer::grid_span`] compiled for the tracer's instruction set.
        fn grid_span_isa / grid_span_avx2<S: GridSink>(
            &self,
            j: u32,
            columns: std::ops::Range<u32>,
            ctx: &mut Ctx,
            sink: &mut S,
        ) -> () {
            self.grid_span_in(j, columns, ctx, sink)
        }
    }

    /// [`Tracer::grid_span`] within a span's state: each pixel's samples row by row,
    /// traced four at a time (the last group may be smaller), summed in sample order.
    #[inline(always)]
    fn grid_span_in(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        ctx: &mut Ctx,
        sink: &mut impl GridSink,
    ) {
        if columns.is_empty() {
            return;
        }
        if self.groups.len() == 1 && self.groups[0].count == 1 {
            return self.single_sample_span(j, columns, ctx, sink);
        }
        // The directions of the next group are computed before the current group is
        // traced: their square root and divisions are a long chain, which then
        // overlaps with the tracing instead of delaying the start of each packet.
        let (mut i, mut g) = (columns.start, 0);
        let mut dir = self.directions_of(i, j, g);
        let mut sum = Vec3::ZERO;
        loop {
            let count = self.groups[g].count;
            let (next_i, next_g) = if g + 1 < self.groups.len() {
                (i, g + 1)
            } else {
                (i + 1, 0)
            };
            let more = next_i < columns.end;
            // No closure here: it could be compiled apart, without the AVX2 features.
            let next = if more {
                self.directions_of(next_i, j, next_g)
            } else {
                dir
            };
            let colors = self.trace_directions(dir, count, ctx);
            sink.samples(&colors, count);
            for k in 0..count {
                sum += colors.lane(k);
            }
            if next_g == 0 {
                sink.pixel(sum);
                sum = Vec3::ZERO;
            }
            if !more {
                return;
            }
            (i, g, dir) = (next_i, next_g, next);
        }
    }

    /// [`Tracer::grid_span_in`] with one sample per pixel (aa = 1): four neighbouring
    /// pixels' camera rays go as one packet, as a pixel's four samples do at higher aa.
    /// Each lane computes what the pixel's own group would, so the bits are the same.
    #[inline(always)]
    fn single_sample_span(
        &self,
        j: u32,
        columns: std::ops::Range<u32>,
        ctx: &mut Ctx,
        sink: &mut impl GridSink,
    ) {
        let mut i = columns.start;
        let mut dir = self.row_directions(i, j, columns.end);
        loop {
            let count = ((columns.end - i) as usize).min(LANES);
            let next_i = i + count as u32;
            let more = next_i < columns.end;
            let next = if more {
                self.row_directions(next_i, j, columns.end)
            } else {
                dir
            };
            let colors = self.trace_directions(dir, count, ctx);
            for k in 0..count {
                let color = colors.lane(k);
                sink.samples(&V4::splat(color), 1);
                let mut sum = Vec3::ZERO;
                sum += color;
                sink.pixel(sum);
            }
            if !more {
                return;
            }
            (i, dir) = (next_i, next);
        }
    }

    /// The single-sample camera directions of the pixels `i .. i + 4` of row `j`
    /// (lanes at or past `end` repeat pixel `i`).
    #[inline(always)]
    fn row_directions(&self, i: u32, j: u32, end: u32) -> V4 {
        let column = |k: usize| {
            let c = i + k as u32;
            if c < end {
                c
            } else {
                i
            }
        };
        let group = &self.groups[0];
        if self.plane_xs.is_empty() {
            let x0 = F4(std::array::from_fn(|k| f64::from(column(k))));
            self.camera
                .directions(x0 + group.sx, F4::splat(f64::from(j)) + group.sy)
        } else {
            let x = F4(std::array::from_fn(|k| {
                self.plane_xs[column(k) as usize].0[0]
            }));
            self.camera.directions_at(x, self.plane_ys[j as usize])
        }
    }

    /// The camera directions of group `g` of pixel (`i`, `j`).
    #[inline(always)]
    fn directions_of(&self, i: u32, j: u32, g: usize) -> V4 {
        if self.plane_xs.is_empty() {
            self.group_directions(i, F4::splat(f64::from(j)), &self.groups[g])
        } else {
            self.table_directions(i, j, g)
        }
    }

    /// The camera directions of a group of samples of the pixel in column `i` (row
    /// `y0`, in every lane): whole vectors, since filling the lanes one by one through
    /// memory would stall the vector loads that follow.
    #[inline(always)]
    fn group_directions(&self, i: u32, y0: F4, group: &SampleGroup) -> V4 {
        let x0 = F4::splat(f64::from(i));
        self.camera.directions(x0 + group.sx, y0 + group.sy)
    }

    /// [`Tracer::group_directions`] of group `g` of pixel (`i`, `j`) from the tables of
    /// image-plane coordinates: the same operations, done ahead.
    #[inline(always)]
    fn table_directions(&self, i: u32, j: u32, g: usize) -> V4 {
        let n = self.groups.len();
        let x = self.plane_xs[i as usize * n + g];
        let y = self.plane_ys[j as usize * n + g];
        self.camera.directions_at(x, y)
    }

    /// Traces the camera samples of the first `count` lanes (1 to [`LANES`]) of `dir`,
    /// whose other lanes repeat the first: alone, or as one packet.
    #[inline(always)]
    fn trace_directions(&self, dir: V4, count: usize, ctx: &mut Ctx) -> V4 {
        if count == 1 {
            return V4::splat(self.camera_sample(dir.lane(0), ctx));
        }
        if self.shapes.is_some() {
            return self.general_packet(dir, count, ctx);
        }
        let rays = Packet {
            origin: V4::splat(self.camera.position()),
            dir,
            from: FROM_CAMERA,
            active: M4::first(count),
        };
        self.packet(&rays, Path::CAMERA, ctx)
    }

    /// Traces the camera samples through the image points of the first `count` lanes
    /// (1 to [`LANES`]) of (`px`, `py`), whose other lanes repeat the first: alone, or
    /// as one packet.
    #[inline(always)]
    pub(super) fn trace_group(&self, px: F4, py: F4, count: usize, ctx: &mut Ctx) -> V4 {
        self.trace_directions(self.camera.directions(px, py), count, ctx)
    }
}

//! The fast way to read a valid scene: a strict hand-written scanner for the plain JSON
//! a scene is made of, no `Value` tree for the objects, and the objects read in parallel
//! on the current rayon pool.
//!
//! It only ever answers "here is the scene" or "not me". Anything unusual (any error, a
//! repeated or unknown key, an escape sequence in a key or in a string it reads, a
//! `null`, and also an `"animation"` key, which only the reference reads) gives `None`, and [`super::parse_scene`] then reads the text the reference
//! way, which alone words errors. So the rule here is: when this returns a scene, the
//! reference returns the same scene.
//!
//! That holds because
//! - the scanner accepts only a subset of JSON: white space, objects, arrays, strings
//!   without escapes or control characters, and numbers;
//! - a JSON number gets the bits the reference's `Value::as_f64` gives: a plain one
//!   (`-12`, `0.625`, at most 19 digits) by serde_json's own arithmetic (the digits as a
//!   u64, converted, divided by a power of ten), any other by serde_json itself, which
//!   also refuses a malformed one; numbers in strings go through the same
//!   `str::parse::<f64>` as the reference's;
//! - the lights, camera, image and ambient values are cut out as text and parsed into a
//!   `Value` by serde_json, then checked by the reference's own functions;
//! - the objects are checked as `parse_object` checks them.
//!
//! With more than one thread, the objects array is cut at guessed element starts (a `{`
//! after a `,`) and the pieces are read in parallel. A guess is used only once the piece
//! before it, itself known to start at an element, ends exactly there; otherwise the
//! rest is read in order. So the guesses change the speed, never the answer.

use rayon::prelude::*;
use serde_json::Value;

use crate::scene::{CameraSpec, Object, Scene, Shape};
use crate::settings::RenderSettings;
use crate::vec3::Vec3;

/// When less text than this (in bytes) follows the start of the objects array, the
/// objects are read on one thread.
const PARALLEL_MIN_BYTES: usize = 1 << 20;

/// Pieces of the objects array per thread, when read in parallel.
const PIECES_PER_THREAD: usize = 4;

/// The scene, when the text is a valid scene in plain JSON; `None` otherwise.
pub(super) fn parse(text: &str) -> Option<Scene> {
    let mut c = Cursor { text, pos: 0 };
    let mut lights = None;
    let mut objects = None;
    let mut camera = None;
    let mut image = None;
    let mut ambient = None;
    c.ws();
    c.eat(b'{')?;
    c.ws();
    loop {
        let key = c.string()?;
        c.ws();
        c.eat(b':')?;
        c.ws();
        match key {
            "lights" => set_once(&mut lights, c.value()?)?,
            "objects" => set_once(&mut objects, c.objects()?)?,
            "camera" => set_once(&mut camera, c.value()?)?,
            "image" => set_once(&mut image, c.value()?)?,
            "ambient" => set_once(&mut ambient, c.value()?)?,
            _ => return None,
        }
        c.ws();
        match c.next()? {
            b',' => c.ws(),
            b'}' => break,
            _ => return None,
        }
    }
    c.ws();
    if c.pos != text.len() {
        return None;
    }

    let lights = lights?
        .as_array()?
        .iter()
        .enumerate()
        .map(|(i, v)| super::parse_light(v, &format!("lights[{i}]")).ok())
        .collect::<Option<Vec<_>>>()?;
    let camera = match &camera {
        Some(v) => super::parse_camera(v, "camera").ok()?,
        None => CameraSpec::default(),
    };
    let settings = match &image {
        Some(v) => super::parse_image(v, "image").ok()?,
        None => RenderSettings::default(),
    };
    let ambient = match &ambient {
        Some(v) => {
            let a = super::number(v, "ambient").ok()?;
            if a < 0.0 {
                return None;
            }
            a
        }
        None => 0.2,
    };
    Some(Scene {
        lights,
        objects: objects?,
        camera,
        settings,
        ambient,
    })
}

/// Sets a field once; a second time is a repeated key, left to the reference.
fn set_once<T>(slot: &mut Option<T>, value: T) -> Option<()> {
    match slot {
        Some(_) => None,
        None => {
            *slot = Some(value);
            Some(())
        }
    }
}

/// Where the scanner is in the text. Every method either consumes what it reads and
/// returns `Some`, or returns `None` (the text is not for the fast path).
pub(super) struct Cursor<'a> {
    pub(super) text: &'a str,
    pub(super) pos: usize,
}

/// How a run of objects read from a guessed start ended.
enum End {
    /// The next element starts here, at or after where the run was to stop.
    Next(usize),
    /// The array closed; reading goes on here (just after the `]`).
    Closed(usize),
}

impl<'a> Cursor<'a> {
    fn peek(&self) -> Option<u8> {
        self.text.as_bytes().get(self.pos).copied()
    }

    fn next(&mut self) -> Option<u8> {
        let b = self.peek()?;
        self.pos += 1;
        Some(b)
    }

    fn eat(&mut self, byte: u8) -> Option<()> {
        (self.next()? == byte).then_some(())
    }

    /// JSON white space, as serde_json skips it.
    fn ws(&mut self) {
        let bytes = self.text.as_bytes();
        while let Some(b' ' | b'\t' | b'\n' | b'\r') = bytes.get(self.pos) {
            self.pos += 1;
        }
    }

    /// A string with no escape and no control character, without its quotes.
    fn string(&mut self) -> Option<&'a str> {
        self.eat(b'"')?;
        let start = self.pos;
        let bytes = self.text.as_bytes();
        loop {
            match *bytes.get(self.pos)? {
                b'"' => break,
                b'\\' | 0..=0x1f => return None,
                _ => self.pos += 1,
            }
        }
        let s = self.text.get(start..self.pos)?;
        self.pos += 1;
        Some(s)
    }

    /// A JSON number, as the reference's `Value` holds it: serde_json's own arithmetic
    /// for the common forms (`-12`, `0.625`, at most 19 digits), serde_json itself for
    /// the rest.
    pub(super) fn number(&mut self) -> Option<f64> {
        let start = self.pos;
        let bytes = self.text.as_bytes();
        let negative = bytes.get(self.pos) == Some(&b'-');
        if negative {
            self.pos += 1;
        }
        let int_start = self.pos;
        let mut significand = self.digits(0);
        let int_digits = self.pos - int_start;
        // No digit, or a leading zero followed by more digits: serde_json refuses both.
        if int_digits == 0 || (int_digits > 1 && bytes[int_start] == b'0') {
            return None;
        }
        let mut decimals = 0;
        if bytes.get(self.pos) == Some(&b'.') {
            self.pos += 1;
            let frac_start = self.pos;
            significand = self.digits(significand);
            decimals = self.pos - frac_start;
            if decimals == 0 {
                return None;
            }
        }
        // Up to 19 digits cannot overflow a u64, where serde_json changes method.
        if int_digits + decimals > 19 {
            return self.number_by_serde_json(start);
        }
        match bytes.get(self.pos) {
            Some(b'e' | b'E') => return self.number_by_serde_json(start),
            // Not a number's end ("1.2.3", "1-2"): serde_json refuses it too.
            Some(b'0'..=b'9' | b'-' | b'+' | b'.') => return None,
            _ => {}
        }
        // serde_json (without its `float_roundtrip` feature): the significand as an
        // f64, divided by the power of ten, then the sign. For an integer that is also
        // what `Value::as_f64` gives, u64 or i64 alike, rounding being symmetric.
        let mut x = significand as f64;
        if decimals > 0 {
            x /= POW10[decimals];
        }
        Some(if negative { -x } else { x })
    }

    /// Reads decimal digits onto `significand` (wrapping on overflow: the caller
    /// counts the digits), eight at a time while it can.
    fn digits(&mut self, mut significand: u64) -> u64 {
        let bytes = self.text.as_bytes();
        while let Some(eight) = bytes.get(self.pos..self.pos + 8) {
            let word = u64::from_le_bytes(eight.try_into().expect("8 bytes"));
            let values = word.wrapping_sub(0x3030_3030_3030_3030);
            // A byte above b'9' sets its top bit in the sum, one below b'0' in the
            // difference.
            if (word.wrapping_add(0x4646_4646_4646_4646) | values) & 0x8080_8080_8080_8080 != 0 {
                break;
            }
            // Pairs, then quadruples, then all eight (the first digit is the lowest byte).
            let pairs = values.wrapping_mul(10).wrapping_add(values >> 8);
            let mask = 0x0000_00ff_0000_00ff;
            let eight = ((pairs & mask)
                .wrapping_mul(100 + (1_000_000 << 32))
                .wrapping_add(((pairs >> 16) & mask).wrapping_mul(1 + (10_000 << 32))))
                >> 32;
            significand = significand.wrapping_mul(100_000_000).wrapping_add(eight);
            self.pos += 8;
        }
        while let Some(&d @ b'0'..=b'9') = bytes.get(self.pos) {
            significand = significand
                .wrapping_mul(10)
                .wrapping_add(u64::from(d - b'0'));
            self.pos += 1;
        }
        significand
    }

    /// The number token starting at `start`, parsed by serde_json.
    #[cold]
    fn number_by_serde_json(&mut self, start: usize) -> Option<f64> {
        let bytes = self.text.as_bytes();
        self.pos = start;
        while let Some(b'0'..=b'9' | b'-' | b'+' | b'.' | b'e' | b'E') = bytes.get(self.pos) {
            self.pos += 1;
        }
        serde_json::from_str::<f64>(self.text.get(start..self.pos)?).ok()
    }

    /// A list of numbers: a string of words or an array.
    fn numbers(&mut self) -> Option<Numbers> {
        let mut n = Numbers {
            len: 0,
            values: [0.0; 4],
        };
        if self.peek()? == b'"' {
            for word in self.string()?.split_whitespace() {
                n.push(word.parse::<f64>().ok()?)?;
            }
            return Some(n);
        }
        self.eat(b'[')?;
        self.ws();
        if self.peek()? == b']' {
            self.pos += 1;
            return Some(n);
        }
        loop {
            n.push(self.number()?)?;
            self.ws();
            match self.next()? {
                b',' => self.ws(),
                b']' => return Some(n),
                _ => return None,
            }
        }
    }

    /// Any JSON value, cut out and parsed by serde_json.
    fn value(&mut self) -> Option<Value> {
        let start = self.pos;
        let bytes = self.text.as_bytes();
        match self.peek()? {
            b'"' => {
                self.pos += 1;
                self.skip_string_body()?;
            }
            b'{' | b'[' => {
                let mut depth = 0usize;
                loop {
                    match self.next()? {
                        b'{' | b'[' => depth += 1,
                        b'}' | b']' => {
                            depth -= 1;
                            if depth == 0 {
                                break;
                            }
                        }
                        b'"' => self.skip_string_body()?,
                        _ => {}
                    }
                }
            }
            _ => {
                while let Some(&b) = bytes.get(self.pos) {
                    if matches!(b, b',' | b'}' | b']' | b' ' | b'\t' | b'\n' | b'\r') {
                        break;
                    }
                    self.pos += 1;
                }
            }
        }
        serde_json::from_str(self.text.get(start..self.pos)?).ok()
    }

    /// The rest of a string after its opening quote, escapes and all (serde_json checks
    /// it afterwards).
    fn skip_string_body(&mut self) -> Option<()> {
        loop {
            match self.next()? {
                b'"' => return Some(()),
                b'\\' => {
                    self.next()?;
                }
                _ => {}
            }
        }
    }

    /// The objects array, read in parallel when it is long and there are threads.
    fn objects(&mut self) -> Option<Vec<Object>> {
        self.eat(b'[')?;
        self.ws();
        if self.peek()? == b']' {
            self.pos += 1;
            return Some(Vec::new());
        }
        let threads = rayon::current_num_threads();
        if threads > 1 && self.text.len() - self.pos >= PARALLEL_MIN_BYTES {
            self.objects_in_parallel(threads)
        } else {
            let mut objects = Vec::new();
            match self.run(&mut objects, usize::MAX)? {
                End::Closed(pos) => self.pos = pos,
                End::Next(_) => unreachable!("a run without a stop ends with the array"),
            }
            Some(objects)
        }
    }

    /// Reads objects, the first one starting here, until the next one would start at or
    /// after `stop` or the array closes.
    fn run(&mut self, objects: &mut Vec<Object>, stop: usize) -> Option<End> {
        loop {
            objects.push(self.object()?);
            self.ws();
            match self.next()? {
                b',' => {
                    self.ws();
                    if self.pos >= stop {
                        return Some(End::Next(self.pos));
                    }
                }
                b']' => return Some(End::Closed(self.pos)),
                _ => return None,
            }
        }
    }

    /// Cuts the rest of the text into a few pieces per thread at guessed element starts,
    /// reads the pieces in parallel, then keeps the pieces whose start was confirmed by
    /// the piece before, in order. Several pieces per thread even out the threads'
    /// work, and keep small the memory of the pieces not yet copied into the whole.
    fn objects_in_parallel(&mut self, threads: usize) -> Option<Vec<Object>> {
        let text = self.text;
        let first = self.pos;
        let len = text.len() - first;
        let pieces = threads * PIECES_PER_THREAD;
        let mut starts = vec![first];
        for k in 1..pieces {
            match guess_element_start(text, first + len / pieces * k) {
                Some(s) if s > *starts.last().unwrap() => starts.push(s),
                _ => {}
            }
        }
        let runs: Vec<Option<(Vec<Object>, End)>> = starts
            .par_iter()
            .enumerate()
            .map(|(k, &start)| {
                let stop = starts.get(k + 1).copied().unwrap_or(usize::MAX);
                let mut c = Cursor { text, pos: start };
                let mut objects = Vec::new();
                let end = c.run(&mut objects, stop)?;
                Some((objects, end))
            })
            .collect();

        let mut runs = runs.into_iter();
        let mut all = Vec::new();
        for k in 0.. {
            // The start of run k is known to be an element: the first run's is, and each
            // later one's was confirmed by the run before.
            let (objects, end) = runs.next().flatten()?;
            if all.is_empty() {
                all = objects;
            } else {
                all.extend_from_slice(&objects);
            }
            match end {
                End::Closed(pos) => {
                    self.pos = pos;
                    return Some(all);
                }
                End::Next(pos) if starts.get(k + 1) == Some(&pos) => {}
                End::Next(pos) => {
                    // The guess was no element start: read on in order from the real one.
                    self.pos = pos;
                    match self.run(&mut all, usize::MAX)? {
                        End::Closed(pos) => self.pos = pos,
                        End::Next(_) => unreachable!("a run without a stop ends with the array"),
                    }
                    return Some(all);
                }
            }
        }
        unreachable!("the last run has no stop")
    }

    /// One object, checked as the reference's `parse_object` checks it.
    fn object(&mut self) -> Option<Object> {
        self.eat(b'{')?;
        self.ws();
        let mut f = Fields::default();
        loop {
            let key = self.string()?;
            self.ws();
            self.eat(b':')?;
            self.ws();
            match key {
                "type" => {
                    let kind = match self.string()? {
                        "sphere" => Kind::Sphere,
                        "plan" | "plane" => Kind::Plane,
                        _ => return None,
                    };
                    set_once(&mut f.kind, kind)?
                }
                "center" => set_once(&mut f.center, self.numbers()?)?,
                "radius" => set_once(&mut f.radius, self.number()?)?,
                "color" => set_once(&mut f.color, self.numbers()?)?,
                "normal" => set_once(&mut f.normal, self.numbers()?)?,
                "distance" => set_once(&mut f.distance, self.number()?)?,
                _ => return None,
            }
            self.ws();
            match self.next()? {
                b',' => self.ws(),
                b'}' => break,
                _ => return None,
            }
        }
        convert(f)
    }
}

/// The first `{` at or after `from` that follows a `,` (and white space): likely, not
/// surely, the start of an element of the objects array.
fn guess_element_start(text: &str, from: usize) -> Option<usize> {
    let bytes = text.as_bytes();
    let mut i = from.max(1);
    loop {
        i += bytes.get(i..)?.iter().position(|&b| b == b'{')?;
        let before = bytes[..i]
            .iter()
            .rev()
            .find(|b| !matches!(b, b' ' | b'\t' | b'\n' | b'\r'));
        if before == Some(&b',') {
            return Some(i);
        }
        i += 1;
    }
}

/// Powers of ten as serde_json's table has them (Rust literals, correctly rounded).
const POW10: [f64; 20] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19,
];

/// An object's `type`.
#[derive(Clone, Copy)]
enum Kind {
    Sphere,
    Plane,
}

/// Up to four finite numbers; more are refused (the format has no longer list).
#[derive(Clone, Copy)]
struct Numbers {
    len: usize,
    values: [f64; 4],
}

impl Numbers {
    fn push(&mut self, x: f64) -> Option<()> {
        if self.len == self.values.len() || !x.is_finite() {
            return None;
        }
        self.values[self.len] = x;
        self.len += 1;
        Some(())
    }

    /// Three numbers as a vector (what the reference's `vec3` accepts).
    fn vec3(&self) -> Option<Vec3> {
        match self.values[..self.len] {
            [x, y, z] => Some(Vec3::new(x, y, z)),
            _ => None,
        }
    }
}

/// The fields of one object as written, each at most once.
#[derive(Default)]
struct Fields {
    kind: Option<Kind>,
    center: Option<Numbers>,
    radius: Option<f64>,
    color: Option<Numbers>,
    normal: Option<Numbers>,
    distance: Option<f64>,
}

/// One object from its fields, checked as the reference's `parse_object` checks it.
fn convert(f: Fields) -> Option<Object> {
    let shape = match f.kind? {
        Kind::Sphere => {
            if f.normal.is_some() || f.distance.is_some() {
                return None;
            }
            let center = f.center?.vec3()?;
            let radius = f.radius?;
            // JSON numbers are finite here: serde_json refuses the others.
            if radius <= 0.0 {
                return None;
            }
            Shape::Sphere { center, radius }
        }
        Kind::Plane => {
            if f.center.is_some() || f.radius.is_some() {
                return None;
            }
            let normal = f.normal?.vec3()?;
            let len = normal.length();
            if len == 0.0 || !len.is_finite() {
                return None;
            }
            Shape::Plane {
                normal,
                distance: f.distance?,
            }
        }
    };
    let color = f.color?;
    let [r, g, b, special] = match color.values[..color.len] {
        [r, g, b, s] => [r, g, b, s],
        _ => return None,
    };
    if r < 0.0 || g < 0.0 || b < 0.0 {
        return None;
    }
    let material = super::material(special, "").ok()?;
    Some(Object {
        shape,
        color: Vec3::new(r, g, b),
        material,
    })
}

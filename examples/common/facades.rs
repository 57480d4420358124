//! The flags that choose the generated facades an evaluation runs on (`--seeds N`,
//! `--first K`, `--views N`, `--size WxH`), shared by the examples on
//! `synth::facade::parallax_case`.

/// Seeds `first..first + seeds`, `views` views each, `width × height`.
#[derive(Debug, Clone, Copy)]
pub struct Facades {
    pub seeds: u64,
    pub first: u64,
    pub views: usize,
    pub width: usize,
    pub height: usize,
}

impl Facades {
    /// `seeds` seeds from 1, `views` views, 640 × 480.
    pub fn new(seeds: u64, views: usize) -> Self {
        Self { seeds, first: 1, views, width: 640, height: 480 }
    }

    /// Takes `flag` and its value from `rest` when it is one of these flags (`true`);
    /// `false` for any other flag. Panics on a missing or malformed value.
    pub fn read<'a>(&mut self, flag: &str, rest: &mut impl Iterator<Item = &'a String>) -> bool {
        let mut value = |usage: &str| rest.next().cloned().unwrap_or_else(|| panic!("{usage}"));
        match flag {
            "--seeds" => self.seeds = value("--seeds N").parse().expect("--seeds N"),
            "--first" => self.first = value("--first K").parse().expect("--first K"),
            "--views" => self.views = value("--views N").parse().expect("--views N"),
            "--size" => {
                let size = value("--size WxH");
                let (w, h) = size.split_once('x').expect("--size WxH");
                (self.width, self.height) = (w.parse().expect("width"), h.parse().expect("height"));
            }
            _ => return false,
        }
        true
    }

    /// The seeds, in order.
    pub fn seed_range(&self) -> std::ops::Range<u64> {
        self.first..self.first + self.seeds
    }
}

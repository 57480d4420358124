//! What the files of a session folder mean (pure policy, no disk): which image is the
//! keyframe and why, which file is whose mask. Every function works on a [`Listing`] of
//! the folder's file names, so the rules are tested here without a disk; the folder
//! source ([`super::folder`]) lists the folder and acts on the answers.
//!
//! Naming rules (README, "Running the service"):
//! - `key.<ext>` is the keyframe; else the image the configuration names
//!   (`session.keyframe`); else the image a mask names (`<stem>.mask.<ext>`,
//!   `<stem>_mask.<ext>`, `<stem>-mask.<ext>`); else the first image to arrive.
//! - `mask.<ext>` is the mask of whatever the keyframe is; a keyframe's own mask wins over it.
//! - A mask is never a view.

use super::watch::{self, Role};
use crate::config::KeyframeRule;

/// Why an image is (or would be) a session's keyframe, strongest first: a later image
/// with a stronger reason takes the keyframe's place, a weaker one never does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum KeySource {
    /// Named `key.<ext>`.
    NamedKey,
    /// Named by the configuration (`session.keyframe`).
    Configured,
    /// A mask beside it names it (`<stem>.mask.png`, `<stem>_mask.*`, `<stem>-mask.*`).
    Masked,
    /// The first image to arrive (`session.keyframe = "first"`).
    First,
    /// Chosen from a video stream ([`super::video`]).
    Video,
}

impl KeySource {
    /// As events write it (`key_source`).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::NamedKey => "named_key",
            Self::Configured => "configured",
            Self::Masked => "masked",
            Self::First => "first",
            Self::Video => "video",
        }
    }
}

/// The names of the regular files of a session folder, and the extensions configured.
#[derive(Debug, Clone, Default)]
pub struct Listing {
    names: Vec<String>,
    extensions: Vec<String>,
}

impl Listing {
    pub fn new(mut names: Vec<String>, extensions: &[String]) -> Self {
        names.sort();
        Self { names, extensions: extensions.to_vec() }
    }

    pub fn has(&self, name: &str) -> bool {
        self.names.binary_search_by(|n| n.as_str().cmp(name)).is_ok()
    }

    /// What file `name` is, if it is a candidate at all (an image of a configured
    /// extension, not hidden, not an upload in progress).
    pub fn role(&self, name: &str) -> Option<Role> {
        if watch::is_partial_or_hidden(name) {
            return None;
        }
        let (stem, ext) = name.rsplit_once('.')?;
        (!stem.is_empty() && self.extensions.iter().any(|e| e.eq_ignore_ascii_case(ext)))
            .then(|| watch::role_of_stem(stem))
    }

    /// Whether there is a `key.<ext>`.
    pub fn has_named_key(&self) -> bool {
        self.extensions.iter().any(|e| self.has(&format!("key.{e}")))
    }

    /// Whether the image of stem `stem` has a mask of its own beside it.
    pub fn has_own_mask(&self, stem: &str) -> bool {
        watch::mask_names(stem, &self.extensions).iter().any(|n| self.has(n))
    }

    /// The mask file of the keyframe `key_name`: its own (`<stem>.mask.<ext>`,
    /// `<stem>_mask.<ext>`, `<stem>-mask.<ext>`, in that order), else the session's
    /// `mask.<ext>`.
    pub fn mask_for(&self, key_name: &str) -> Option<String> {
        let own = watch::mask_names(watch::stem(key_name), &self.extensions);
        let shared = self.extensions.iter().map(|e| format!("mask.{e}"));
        own.into_iter().chain(shared).find(|n| self.has(n))
    }

    /// The image (not a mask) of stem `owner`, the first by name if there are several.
    pub fn image_of(&self, owner: &str) -> Option<&str> {
        self.names
            .iter()
            .map(String::as_str)
            .find(|n| watch::stem(n) == owner && self.role(n).is_some_and(|r| r != Role::Mask))
    }
}

/// The session's keyframe as it stands: its file name and why it is the keyframe, and
/// the name the saved state remembers (from before a restart or a sleep).
#[derive(Debug, Clone, Copy, Default)]
pub struct KeyNow<'a> {
    pub current: Option<(&'a str, KeySource)>,
    pub saved: Option<&'a str>,
}

/// Why image `name` would become the keyframe now, or `None` if it is a view (or must
/// wait for the keyframe).
pub fn key_source_for(rule: &KeyframeRule, listing: &Listing, key: KeyNow, name: &str) -> Option<KeySource> {
    let stem = watch::stem(name);
    if let Some((current, source)) = key.current
        && current == name
    {
        // A new version of the keyframe.
        return Some(source);
    }
    let beats = |s: KeySource| key.current.is_none_or(|(_, k)| s < k);
    match rule {
        KeyframeRule::Named(n) if n == stem => beats(KeySource::Configured).then_some(KeySource::Configured),
        KeyframeRule::Named(_) => None,
        KeyframeRule::First => {
            if listing.has_named_key() {
                return None;
            }
            if listing.has_own_mask(stem) {
                // The image the user painted a mask for, whatever arrived first.
                return beats(KeySource::Masked).then_some(KeySource::Masked);
            }
            if key.current.is_some() {
                return None;
            }
            if let Some(saved) = key.saved
                && saved != name
                && listing.has(saved)
            {
                return None;
            }
            Some(KeySource::First)
        }
    }
}

/// Why the keyframe the saved state names (`name`) is the keyframe, when a sleeping
/// session is woken.
pub fn saved_key_source(rule: &KeyframeRule, listing: &Listing, name: &str) -> KeySource {
    match (rule, watch::stem(name)) {
        (_, "key") => KeySource::NamedKey,
        (KeyframeRule::Named(n), s) if n == s => KeySource::Configured,
        (_, s) if listing.has_own_mask(s) => KeySource::Masked,
        _ => KeySource::First,
    }
}

/// The image that mask file `mask` names and that should become the keyframe because of
/// it: when the mask names an image (not `mask.<ext>`), that image is not the keyframe,
/// and the keyframe was chosen for a weaker reason than a mask (the first to arrive).
pub fn key_named_by_mask<'a>(
    rule: &KeyframeRule,
    listing: &'a Listing,
    key: KeyNow,
    mask: &str,
) -> Option<&'a str> {
    let owner = watch::mask_owner(watch::stem(mask)).filter(|o| !o.is_empty())?;
    let weaker = key.current.is_none_or(|(_, k)| k > KeySource::Masked);
    let current_stem = key.current.map(|(n, _)| watch::stem(n));
    if !weaker || current_stem == Some(owner) || !matches!(rule, KeyframeRule::First) {
        return None;
    }
    listing.image_of(owner)
}

/// What a mask file is to the keyframe `key_name`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MaskFit {
    /// It is the keyframe's mask.
    Applies,
    /// It names another image (its stem) than the keyframe.
    OtherImage(String),
    /// It is the session's `mask.<ext>`, but the keyframe has a mask of its own.
    Shadowed,
}

/// Whether mask file `mask` is the mask of the keyframe `key_name`.
pub fn mask_fit(listing: &Listing, key_name: &str, mask: &str) -> MaskFit {
    let owner = watch::mask_owner(watch::stem(mask)).unwrap_or_default();
    let key_stem = watch::stem(key_name);
    if !owner.is_empty() && owner != key_stem {
        MaskFit::OtherImage(owner.to_owned())
    } else if owner.is_empty() && listing.has_own_mask(key_stem) {
        MaskFit::Shadowed
    } else {
        MaskFit::Applies
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn listing(names: &[&str]) -> Listing {
        let ext: Vec<String> = ["jpg", "png"].iter().map(|e| (*e).to_owned()).collect();
        Listing::new(names.iter().map(|n| (*n).to_owned()).collect(), &ext)
    }

    const FIRST: KeyframeRule = KeyframeRule::First;

    #[test]
    fn a_session_copied_at_once_keys_the_masked_image_whatever_lands_first() {
        let l = listing(&["hunt1.jpg", "hunt2.jpg", "hunt3.jpg", "hunt3.mask.png", "hunt4.jpg"]);
        let none = KeyNow::default();
        // hunt1 lands first and is keyed for now (first come); hunt3, whose mask is there,
        // is keyed whenever it lands, before hunt1 or after.
        assert_eq!(key_source_for(&FIRST, &l, none, "hunt1.jpg"), Some(KeySource::First));
        assert_eq!(key_source_for(&FIRST, &l, none, "hunt3.jpg"), Some(KeySource::Masked));
        let hunt1 = KeyNow { current: Some(("hunt1.jpg", KeySource::First)), saved: None };
        assert_eq!(key_source_for(&FIRST, &l, hunt1, "hunt3.jpg"), Some(KeySource::Masked));
        assert_eq!(key_source_for(&FIRST, &l, hunt1, "hunt2.jpg"), None, "a view");
        let hunt3 = KeyNow { current: Some(("hunt3.jpg", KeySource::Masked)), saved: None };
        assert_eq!(key_source_for(&FIRST, &l, hunt3, "hunt1.jpg"), None, "never back to the first");
        // The mask landing after its image names it.
        assert_eq!(key_named_by_mask(&FIRST, &l, hunt1, "hunt3.mask.png"), Some("hunt3.jpg"));
        // ...but never over key.jpg.
        let key = KeyNow { current: Some(("key.jpg", KeySource::NamedKey)), saved: None };
        assert_eq!(key_named_by_mask(&FIRST, &l, key, "hunt3.mask.png"), None);
        // A session-wide mask.png names no image.
        assert_eq!(key_named_by_mask(&FIRST, &l, hunt1, "mask.png"), None);
    }

    #[test]
    fn masks_are_named_every_way_people_write_them_and_are_never_images() {
        for mask in ["hunt3.mask.png", "hunt3_mask.png", "hunt3-mask.jpg", "hunt3_MASK.png"] {
            let l = listing(&["hunt1.jpg", "hunt3.jpg", mask]);
            assert_eq!(l.role(mask), Some(Role::Mask), "{mask}");
            assert!(l.has_own_mask("hunt3") || mask.contains("MASK"), "{mask}");
            assert_eq!(l.image_of("hunt3"), Some("hunt3.jpg"), "{mask}");
        }
        let l = listing(&["a.jpg", "a_mask.png", "mask.png", ".hidden.jpg", "b.jpg.part", "notes.txt"]);
        assert_eq!(l.role("key.jpg"), Some(Role::Key));
        assert_eq!(l.role("mask.png"), Some(Role::Mask));
        assert_eq!(l.role(".hidden.jpg"), None);
        assert_eq!(l.role("b.jpg.part"), None);
        assert_eq!(l.role("notes.txt"), None);
        // The keyframe's own mask first, then the session's.
        assert_eq!(l.mask_for("a.jpg").as_deref(), Some("a_mask.png"));
        assert_eq!(l.mask_for("b.jpg").as_deref(), Some("mask.png"));
        assert_eq!(mask_fit(&l, "a.jpg", "mask.png"), MaskFit::Shadowed);
        assert_eq!(mask_fit(&l, "a.jpg", "a_mask.png"), MaskFit::Applies);
        assert_eq!(mask_fit(&l, "b.jpg", "a_mask.png"), MaskFit::OtherImage("a".into()));
        assert_eq!(mask_fit(&l, "b.jpg", "mask.png"), MaskFit::Applies);
    }

    #[test]
    fn named_keys_and_configuration_beat_masks_and_the_first_image() {
        let l = listing(&["key.jpg", "v1.jpg", "v1.mask.png"]);
        let none = KeyNow::default();
        assert_eq!(key_source_for(&FIRST, &l, none, "v1.jpg"), None, "key.jpg is there");
        let named = KeyframeRule::Named("v2".into());
        let l = listing(&["v1.jpg", "v2.jpg", "v1.mask.png"]);
        assert_eq!(key_source_for(&named, &l, none, "v1.jpg"), None);
        assert_eq!(key_source_for(&named, &l, none, "v2.jpg"), Some(KeySource::Configured));
        assert_eq!(key_named_by_mask(&named, &l, none, "v1.mask.png"), None);
        // First come, first keyed; a new version of the keyframe stays the keyframe.
        let l = listing(&["v1.jpg", "v2.jpg"]);
        assert_eq!(key_source_for(&FIRST, &l, none, "v1.jpg"), Some(KeySource::First));
        let v1 = KeyNow { current: Some(("v1.jpg", KeySource::First)), saved: None };
        assert_eq!(key_source_for(&FIRST, &l, v1, "v2.jpg"), None);
        assert_eq!(key_source_for(&FIRST, &l, v1, "v1.jpg"), Some(KeySource::First));
        // After a restart the saved keyframe, still there, keeps its place.
        let saved = KeyNow { current: None, saved: Some("v2.jpg") };
        assert_eq!(key_source_for(&FIRST, &l, saved, "v1.jpg"), None);
        let gone = KeyNow { current: None, saved: Some("v9.jpg") };
        assert_eq!(key_source_for(&FIRST, &l, gone, "v1.jpg"), Some(KeySource::First));
        assert_eq!(saved_key_source(&FIRST, &listing(&["a.jpg", "a-mask.png"]), "a.jpg"), KeySource::Masked);
        assert_eq!(saved_key_source(&FIRST, &l, "key.png"), KeySource::NamedKey);
        assert_eq!(saved_key_source(&named, &l, "v2.jpg"), KeySource::Configured);
        assert_eq!(saved_key_source(&FIRST, &l, "v1.jpg"), KeySource::First);
    }
}

//! A Zarr store is someone else's file: what Isowall puts between `zarrs` and it.
//!
//! - [`register_bounded_codecs`] puts a bounded decoder in front of `zarrs`' own `gzip`, `zstd`
//!   and `blosc` codecs (runtime plugins take precedence over built-in ones): each chunk decodes
//!   to at most the size its shape gives, and a chunk that would decode to more is refused as soon
//!   as the excess is seen. `zarrs`' gzip reads to the end of the stream and its zstd trusts the
//!   frame's own content size, so a small bomb chunk could otherwise take all memory.
//! - [`BoundedStore`] refuses any read of a value larger than the store's largest honest chunk
//!   (or metadata document) before it reads it.
//!
//! Encoding goes to `zarrs`' codecs unchanged.

use std::borrow::Cow;
use std::io::Read;
use std::sync::{Arc, Once};

use zarrs::array::codec::api::{
    ArrayBytesRaw, BytesRepresentation, BytesToBytesCodecTraits, Codec, CodecError, CodecMetadataOptions,
    CodecOptions, CodecRuntimePluginV2, CodecRuntimePluginV3, CodecTraits, CodecTraitsV2, CodecTraitsV3,
    PartialDecoderCapability, PartialEncoderCapability, RecommendedConcurrency,
};
use zarrs::array::codec::{BloscCodec, GzipCodec, ZstdCodec};
use zarrs::metadata::Configuration;
use zarrs::plugin::{ExtensionName, PluginCreateError, ZarrVersion};
use zarrs::storage::byte_range::{ByteRange, ByteRangeIterator};
use zarrs::storage::{MaybeBytesIterator, ReadableStorageTraits, StorageError, StoreKey};

/// The compressions whose decoders Isowall bounds, by their Zarr name (v2 and v3 alike).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    Gzip,
    Zstd,
    Blosc,
}

impl Compression {
    pub const ALL: [Compression; 3] = [Compression::Gzip, Compression::Zstd, Compression::Blosc];

    /// The codec's name in Zarr metadata (v3 `name`, v2 `id`).
    pub fn name(self) -> &'static str {
        match self {
            Compression::Gzip => "gzip",
            Compression::Zstd => "zstd",
            Compression::Blosc => "blosc",
        }
    }
}

/// Registers the bounded decoders once per process (before any store is opened).
pub fn register_bounded_codecs() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        for c in Compression::ALL {
            zarrs::array::codec::api::register_codec_v3(CodecRuntimePluginV3::new(
                move |name| name == c.name(),
                move |m| Ok(Bounded::wrap(c, inner_v3(c, m)?)),
            ));
            zarrs::array::codec::api::register_codec_v2(CodecRuntimePluginV2::new(
                move |name| name == c.name(),
                move |m| Ok(Bounded::wrap(c, inner_v2(c, m)?)),
            ));
        }
    });
}

fn inner_v3(c: Compression, m: &zarrs::metadata::v3::MetadataV3) -> Result<Codec, PluginCreateError> {
    match c {
        Compression::Gzip => <GzipCodec as CodecTraitsV3>::create(m),
        Compression::Zstd => <ZstdCodec as CodecTraitsV3>::create(m),
        Compression::Blosc => <BloscCodec as CodecTraitsV3>::create(m),
    }
}

fn inner_v2(c: Compression, m: &zarrs::metadata::v2::MetadataV2) -> Result<Codec, PluginCreateError> {
    match c {
        Compression::Gzip => <GzipCodec as CodecTraitsV2>::create(m),
        Compression::Zstd => <ZstdCodec as CodecTraitsV2>::create(m),
        Compression::Blosc => <BloscCodec as CodecTraitsV2>::create(m),
    }
}

/// One of `zarrs`' compression codecs with a decoder that never outgrows the decoded size.
#[derive(Debug)]
struct Bounded {
    compression: Compression,
    inner: Arc<dyn BytesToBytesCodecTraits>,
}

impl Bounded {
    fn wrap(compression: Compression, inner: Codec) -> Codec {
        match inner {
            Codec::BytesToBytes(inner) => Codec::BytesToBytes(Arc::new(Bounded { compression, inner })),
            other => other,
        }
    }
}

/// The most bytes a chunk may decode to: its decoded representation's size. An unbounded one
/// (variable-length data, which Isowall never reads) is refused.
fn decoded_bound(c: Compression, r: &BytesRepresentation) -> Result<u64, CodecError> {
    r.size().ok_or_else(|| {
        CodecError::Other(format!("{}: a chunk of unbounded decoded size is not read", c.name()))
    })
}

fn too_large(c: Compression, bound: u64, what: &str) -> CodecError {
    CodecError::Other(format!(
        "a {} chunk {what} more than the {bound} bytes its shape holds: refused (a corrupt or hostile chunk)",
        c.name()
    ))
}

/// Reads `reader` to its end, refusing it as soon as it gives more than `bound` bytes.
fn read_bounded(c: Compression, reader: impl Read, bound: u64) -> Result<Vec<u8>, CodecError> {
    let mut out = Vec::with_capacity(usize::try_from(bound).unwrap_or(0).min(64 << 20));
    reader
        .take(bound.saturating_add(1))
        .read_to_end(&mut out)
        .map_err(|e| CodecError::Other(format!("a {} chunk does not decode: {e}", c.name())))?;
    if out.len() as u64 > bound {
        return Err(too_large(c, bound, "decodes to"));
    }
    Ok(out)
}

/// The decoded size a blosc header claims (bytes 4..8, little endian), before anything is
/// decompressed.
fn blosc_claim(encoded: &[u8]) -> Option<u64> {
    encoded.get(4..8).map(|b| u64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])))
}

impl ExtensionName for Bounded {
    fn name(&self, version: ZarrVersion) -> Option<Cow<'static, str>> {
        self.inner.name(version)
    }
}

impl CodecTraits for Bounded {
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }

    fn configuration(&self, version: ZarrVersion, options: &CodecMetadataOptions) -> Option<Configuration> {
        self.inner.configuration(version, options)
    }

    fn partial_decoder_capability(&self) -> PartialDecoderCapability {
        // Every read decodes the whole chunk through `decode` (the default partial decoder).
        PartialDecoderCapability { partial_read: false, partial_decode: false }
    }

    fn partial_encoder_capability(&self) -> PartialEncoderCapability {
        PartialEncoderCapability { partial_encode: false }
    }
}

impl BytesToBytesCodecTraits for Bounded {
    fn into_dyn(self: Arc<Self>) -> Arc<dyn BytesToBytesCodecTraits> {
        self
    }

    fn recommended_concurrency(&self, r: &BytesRepresentation) -> Result<RecommendedConcurrency, CodecError> {
        self.inner.recommended_concurrency(r)
    }

    fn encoded_representation(&self, r: &BytesRepresentation) -> BytesRepresentation {
        self.inner.encoded_representation(r)
    }

    fn encode<'a>(
        &self,
        decoded: ArrayBytesRaw<'a>,
        options: &CodecOptions,
    ) -> Result<ArrayBytesRaw<'a>, CodecError> {
        self.inner.encode(decoded, options)
    }

    fn decode<'a>(
        &self,
        encoded: ArrayBytesRaw<'a>,
        decoded_representation: &BytesRepresentation,
        options: &CodecOptions,
    ) -> Result<ArrayBytesRaw<'a>, CodecError> {
        let c = self.compression;
        let bound = decoded_bound(c, decoded_representation)?;
        match c {
            Compression::Gzip => {
                Ok(Cow::Owned(read_bounded(c, flate2::read::GzDecoder::new(&encoded[..]), bound)?))
            }
            Compression::Zstd => {
                let decoder = zstd::stream::read::Decoder::new(&encoded[..])
                    .map_err(|e| CodecError::Other(format!("a zstd chunk does not decode: {e}")))?;
                Ok(Cow::Owned(read_bounded(c, decoder, bound)?))
            }
            Compression::Blosc => {
                // blosc allocates what its header claims: the claim is checked first.
                match blosc_claim(&encoded) {
                    Some(claim) if claim <= bound => {
                        self.inner.decode(encoded, decoded_representation, options)
                    }
                    Some(claim) => Err(too_large(c, bound, &format!("claims {claim} bytes,"))),
                    None => Err(CodecError::Other("a blosc chunk is shorter than its header".into())),
                }
            }
        }
    }
}

/// A store that reads no value larger than `max_read` bytes, checked from its size before it
/// is read.
pub struct BoundedStore<S> {
    inner: S,
    max_read: u64,
}

impl<S: ReadableStorageTraits> BoundedStore<S> {
    pub fn new(inner: S, max_read: u64) -> Self {
        BoundedStore { inner, max_read }
    }
}

impl<S: ReadableStorageTraits> ReadableStorageTraits for BoundedStore<S> {
    fn get_partial_many<'a>(
        &'a self,
        key: &StoreKey,
        byte_ranges: ByteRangeIterator<'a>,
    ) -> Result<MaybeBytesIterator<'a>, StorageError> {
        let Some(size) = self.inner.size_key(key)? else { return Ok(None) };
        let ranges: Vec<ByteRange> = byte_ranges.collect();
        for r in &ranges {
            // The range's length where it lies inside the value (a truncated or lying file
            // asks for more than is there).
            let len = match *r {
                ByteRange::FromStart(start, None) => size.checked_sub(start),
                ByteRange::FromStart(start, Some(len)) => {
                    start.checked_add(len).filter(|&e| e <= size).map(|_| len)
                }
                ByteRange::Suffix(len) => (len <= size).then_some(len),
            };
            let Some(len) = len else {
                return Err(StorageError::Other(format!(
                    "{key}: a read of {r} lies outside its {size} bytes"
                )));
            };
            if len > self.max_read {
                return Err(StorageError::Other(format!(
                    "{key}: a value of {len} bytes is larger than any chunk of this store may be ({} bytes): \
                     refused before it is read",
                    self.max_read
                )));
            }
        }
        self.inner.get_partial_many(key, Box::new(ranges.into_iter()))
    }

    fn size_key(&self, key: &StoreKey) -> Result<Option<u64>, StorageError> {
        self.inner.size_key(key)
    }

    fn supports_get_partial(&self) -> bool {
        self.inner.supports_get_partial()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bound(n: u64) -> BytesRepresentation {
        BytesRepresentation::FixedSize(n)
    }

    fn codec(c: Compression) -> Bounded {
        let inner: Arc<dyn BytesToBytesCodecTraits> = match c {
            Compression::Gzip => Arc::new(GzipCodec::new(5).unwrap()),
            Compression::Zstd => Arc::new(ZstdCodec::new(3, false)),
            Compression::Blosc => Arc::new(
                BloscCodec::new(
                    zarrs::array::codec::BloscCompressor::LZ4,
                    5.try_into().unwrap(),
                    None,
                    zarrs::array::codec::BloscShuffleMode::NoShuffle,
                    Some(1),
                )
                .unwrap(),
            ),
        };
        Bounded { compression: c, inner }
    }

    #[test]
    fn each_codec_decodes_an_honest_chunk_and_refuses_a_bomb() {
        let honest = vec![7u8; 4096];
        let bomb = vec![0u8; 64 << 20];
        for c in Compression::ALL {
            let codec = codec(c);
            let opts = CodecOptions::default();
            let small = codec.encode(Cow::Borrowed(&honest), &opts).unwrap().into_owned();
            let back = codec.decode(Cow::Owned(small), &bound(4096), &opts).unwrap();
            assert_eq!(&back[..], &honest[..], "{c:?}");
            // 64 MiB of zeros in a chunk whose shape holds 4 KiB.
            let big = codec.encode(Cow::Borrowed(&bomb), &opts).unwrap().into_owned();
            assert!(big.len() < 1 << 20, "{c:?}: the bomb is small ({} bytes)", big.len());
            let e = codec.decode(Cow::Owned(big), &bound(4096), &opts).unwrap_err().to_string();
            assert!(e.contains("4096 bytes its shape holds"), "{c:?}: {e}");
        }
    }
}

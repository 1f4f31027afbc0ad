//! Caption embeddings of a corpus: every distinct caption embedded once into
//! `CORPUS/text/<encoder id>/shard-NNNNN.parquet`, resumably, and read back by caption.
//!
//! Shards are fixed slices of the sorted caption list ([`SHARD_CAPTIONS`] each), so a re-run
//! recomputes exactly the shards that are missing: `index.json`, rewritten after every shard,
//! records each finished shard's sha256, and a shard whose file no longer matches is redone.

use crate::{TextEncoder, TokenEmbeddings};
use arrow_array::builder::{Float32Builder, ListBuilder, StringBuilder, UInt32Builder};
use arrow_array::cast::AsArray;
use arrow_array::types::Float32Type;
use arrow_array::{ArrayRef, RecordBatch};
use arrow_schema::{DataType, Field, Schema};
use bytes::Bytes;
use ingest::corpus::manifest::{Manifest, TextEmbeddingEntry};
use ingest::corpus::schema::{col as corpus_col, list_item};
use motionscale_core::write_json;
use nn::ModelError;
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection,
    RowSelector,
};
use parquet::arrow::{ArrowWriter, ProjectionMask};
use parquet::basic::{Compression, Encoding, ZstdLevel};
use parquet::file::properties::WriterProperties;
use parquet::schema::types::{ColumnPath, SchemaDescriptor};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Captions per shard file.
pub const SHARD_CAPTIONS: usize = 4096;
/// Captions per Parquet row group (small, so one caption decodes without its shard).
pub const ROW_GROUP_ROWS: usize = 64;
/// Name of the resume index inside an embedding folder.
pub const INDEX_FILE: &str = "index.json";
/// Schema metadata key holding the encoder id.
pub const META_ENCODER: &str = "motionscale.text_encoder";
/// Schema metadata key holding the embedding width.
pub const META_DIM: &str = "motionscale.text_dim";

/// Column names of an embedding shard.
pub mod col {
    /// The caption text.
    pub const CAPTION: &str = "caption";
    /// Its tokens.
    pub const TOKENS: &str = "tokens";
    /// Number of tokens.
    pub const NUM_TOKENS: &str = "num_tokens";
    /// Flat num_tokens × dim f32 token embeddings.
    pub const EMBEDDINGS: &str = "embeddings";
}

/// The Arrow schema of an embedding shard made by `encoder` (width `dim`).
pub fn shard_schema(encoder: &str, dim: usize) -> Arc<Schema> {
    let metadata = HashMap::from([
        (META_ENCODER.to_string(), encoder.to_string()),
        (META_DIM.to_string(), dim.to_string()),
    ]);
    Arc::new(Schema::new_with_metadata(
        vec![
            Field::new(col::CAPTION, DataType::Utf8, false),
            Field::new(
                col::TOKENS,
                DataType::List(list_item(DataType::Utf8)),
                false,
            ),
            Field::new(col::NUM_TOKENS, DataType::UInt32, false),
            Field::new(
                col::EMBEDDINGS,
                DataType::List(list_item(DataType::Float32)),
                false,
            ),
        ],
        metadata,
    ))
}

/// What [`embed_corpus`] did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EmbedReport {
    /// Encoder id.
    pub encoder: String,
    /// Folder of the shards.
    pub dir: PathBuf,
    /// Embedding width.
    pub dim: usize,
    /// Distinct captions in the corpus.
    pub captions: u64,
    /// Shard files.
    pub shards: u64,
    /// Shards found complete and kept from an earlier run.
    pub skipped_shards: u64,
    /// Captions embedded by this run.
    pub embedded: u64,
    /// Tokens embedded by this run.
    pub tokens: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct IndexShard {
    file: String,
    first: u64,
    rows: u64,
    sha256: String,
}

/// `index.json`: which shards of which caption list are finished.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Index {
    encoder: String,
    dim: usize,
    captions: u64,
    /// sha256 of the sorted captions, so a changed corpus invalidates every shard.
    captions_sha256: String,
    shard_captions: usize,
    shards: Vec<IndexShard>,
}

fn sha256_hex(bytes: &[u8]) -> String {
    motionscale_core::hex(&Sha256::digest(bytes))
}

/// The distinct captions of a corpus, sorted.
pub fn corpus_captions(corpus_dir: &Path) -> Result<Vec<String>, ModelError> {
    let captions: BTreeSet<String> = clip_captions(corpus_dir)?.into_values().flatten().collect();
    Ok(captions.into_iter().collect())
}

/// Every clip's captions by motion id (only the `motion_id` and `captions` columns are
/// decoded).
pub fn clip_captions(corpus_dir: &Path) -> Result<HashMap<String, Vec<String>>, ModelError> {
    let manifest = ingest::corpus::integrity::read_checked(corpus_dir)
        .map_err(|e| ModelError::corpus(corpus_dir, e))?;
    let mut out = HashMap::new();
    for shard in &manifest.shards {
        let path = corpus_dir.join(&shard.file);
        let file = std::fs::File::open(&path).map_err(|e| ModelError::io(&path, e))?;
        let builder = ParquetRecordBatchReaderBuilder::try_new(file)
            .map_err(|e| ModelError::invalid(&path, e))?;
        let mask = projection(
            builder.parquet_schema(),
            builder.schema(),
            &[corpus_col::MOTION_ID, corpus_col::CAPTIONS],
        );
        let reader = builder
            .with_projection(mask)
            .build()
            .map_err(|e| ModelError::invalid(&path, e))?;
        for batch in reader {
            let batch = batch.map_err(|e| ModelError::invalid(&path, e))?;
            let ids = batch
                .column_by_name(corpus_col::MOTION_ID)
                .and_then(|c| c.as_string_opt::<i32>())
                .ok_or_else(|| ModelError::invalid(&path, "motion_id column is not utf8"))?;
            let lists = batch
                .column_by_name(corpus_col::CAPTIONS)
                .and_then(|c| c.as_list_opt::<i32>())
                .ok_or_else(|| ModelError::invalid(&path, "captions column is not a list"))?;
            for (row, id) in ids.iter().enumerate() {
                let id = id.ok_or_else(|| ModelError::invalid(&path, "null motion_id"))?;
                let list = lists.value(row);
                let values = list
                    .as_string_opt::<i32>()
                    .ok_or_else(|| ModelError::invalid(&path, "captions are not utf8"))?;
                let captions = values.iter().flatten().map(str::to_string).collect();
                out.insert(id.to_string(), captions);
            }
        }
    }
    Ok(out)
}

fn projection(descr: &SchemaDescriptor, schema: &Schema, names: &[&str]) -> ProjectionMask {
    let roots = names
        .iter()
        .filter_map(|n| schema.fields().iter().position(|f| f.name() == n));
    ProjectionMask::roots(descr, roots)
}

/// Embed every distinct caption of the corpus in `corpus_dir` with `encoder`, `batch` texts
/// per forward pass, into `CORPUS/text/<encoder id>/`, skipping shards an earlier run
/// finished; then record the embeddings in the corpus manifest (replacing an entry of the
/// same encoder). Calls `progress(captions done, captions total)`.
pub fn embed_corpus(
    corpus_dir: &Path,
    encoder: &dyn TextEncoder,
    batch: usize,
    progress: &dyn Fn(u64, u64),
) -> Result<EmbedReport, ModelError> {
    embed_corpus_sharded(corpus_dir, encoder, batch, SHARD_CAPTIONS, progress)
}

/// [`embed_corpus`] with `shard_captions` captions per shard instead of [`SHARD_CAPTIONS`]
/// (a different size than an earlier run's redoes every shard).
pub fn embed_corpus_sharded(
    corpus_dir: &Path,
    encoder: &dyn TextEncoder,
    batch: usize,
    shard_captions: usize,
    progress: &dyn Fn(u64, u64),
) -> Result<EmbedReport, ModelError> {
    if batch == 0 || shard_captions == 0 {
        return Err(ModelError::argument(
            "batch",
            format!(
                "batch size ({batch}) and captions per shard ({shard_captions}) must be positive"
            ),
        ));
    }
    let captions = corpus_captions(corpus_dir)?;
    let (id, dim) = (encoder.id().to_string(), encoder.dim());
    let rel_dir = format!("text/{id}");
    let out_dir = corpus_dir.join(&rel_dir);
    let mut list_hash = Sha256::new();
    for c in &captions {
        list_hash.update(c.as_bytes());
        list_hash.update(b"\n");
    }
    let fresh = Index {
        encoder: id.clone(),
        dim,
        captions: captions.len() as u64,
        captions_sha256: motionscale_core::hex(&list_hash.finalize()),
        shard_captions,
        shards: Vec::new(),
    };
    let index_path = out_dir.join(INDEX_FILE);
    let previous = read_index(&index_path)?.filter(|old| {
        Index {
            shards: Vec::new(),
            ..old.clone()
        } == fresh
    });
    let slices: Vec<&[String]> = captions.chunks(shard_captions).collect();
    let mut finished: Vec<Option<IndexShard>> = slices
        .iter()
        .enumerate()
        .map(|(k, slice)| {
            let old = previous
                .as_ref()?
                .shards
                .iter()
                .find(|s| s.first == (k * shard_captions) as u64)?;
            let intact = old.rows == slice.len() as u64
                && std::fs::read(out_dir.join(&old.file))
                    .is_ok_and(|b| sha256_hex(&b) == old.sha256);
            intact.then(|| old.clone())
        })
        .collect();
    let total = captions.len() as u64;
    let mut report = EmbedReport {
        encoder: id.clone(),
        dir: out_dir.clone(),
        dim,
        captions: total,
        shards: slices.len() as u64,
        skipped_shards: 0,
        embedded: 0,
        tokens: 0,
    };
    let mut done = 0u64;
    progress(done, total);
    for (k, slice) in slices.iter().enumerate() {
        if finished[k].is_some() {
            report.skipped_shards += 1;
            done += slice.len() as u64;
            progress(done, total);
            continue;
        }
        let embeddings = embed_texts(encoder, slice, batch, &|n| progress(done + n, total))?;
        report.embedded += slice.len() as u64;
        report.tokens += embeddings.iter().map(|e| e.len() as u64).sum::<u64>();
        let bytes = encode_shard(&id, dim, slice, &embeddings)?;
        let file = format!("shard-{k:05}.parquet");
        let path = out_dir.join(&file);
        motionscale_core::write_atomic(&path, &bytes).map_err(|e| ModelError::io(&path, e))?;
        finished[k] = Some(IndexShard {
            file,
            first: (k * shard_captions) as u64,
            rows: slice.len() as u64,
            sha256: sha256_hex(&bytes),
        });
        let index = Index {
            shards: finished.iter().flatten().cloned().collect(),
            ..fresh.clone()
        };
        write_json(&index_path, &index)?;
        done += slice.len() as u64;
        progress(done, total);
    }
    if slices.is_empty() {
        write_json(&index_path, &fresh)?;
    }
    remove_stale_shards(&out_dir, &finished)?;
    let mut manifest = Manifest::read(corpus_dir).map_err(|e| ModelError::corpus(corpus_dir, e))?;
    manifest.text_embeddings.retain(|e| e.encoder != id);
    manifest.text_embeddings.push(TextEmbeddingEntry {
        encoder: id,
        dir: rel_dir,
        dim,
        captions: total,
    });
    manifest
        .write(corpus_dir)
        .map_err(|e| ModelError::corpus(corpus_dir, e))?;
    Ok(report)
}

/// Delete shard files an earlier run (of another caption list or shard size) left behind.
fn remove_stale_shards(dir: &Path, keep: &[Option<IndexShard>]) -> Result<(), ModelError> {
    let keep: BTreeSet<&str> = keep.iter().flatten().map(|s| s.file.as_str()).collect();
    for entry in std::fs::read_dir(dir).map_err(|e| ModelError::io(dir, e))? {
        let path = entry.map_err(|e| ModelError::io(dir, e))?.path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        if name.starts_with("shard-") && name.ends_with(".parquet") && !keep.contains(name) {
            std::fs::remove_file(&path).map_err(|e| ModelError::io(&path, e))?;
        }
    }
    Ok(())
}

fn read_index(path: &Path) -> Result<Option<Index>, ModelError> {
    match std::fs::read_to_string(path) {
        Ok(text) => Ok(serde_json::from_str(&text).ok()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(ModelError::io(path, e)),
    }
}

/// Embed `texts` in batches of `batch` texts of similar length (less padding), returning
/// them in input order; calls `progress(texts done)` after each batch.
pub fn embed_texts(
    encoder: &dyn TextEncoder,
    texts: &[String],
    batch: usize,
    progress: &dyn Fn(u64),
) -> Result<Vec<TokenEmbeddings>, ModelError> {
    let mut order: Vec<usize> = (0..texts.len()).collect();
    order.sort_by_key(|&i| texts[i].len());
    let mut out: Vec<Option<TokenEmbeddings>> = vec![None; texts.len()];
    let mut done = 0u64;
    for chunk in order.chunks(batch) {
        let batch_texts: Vec<&str> = chunk.iter().map(|&i| texts[i].as_str()).collect();
        let embedded = encoder.encode(&batch_texts)?;
        if embedded.len() != chunk.len() {
            return Err(ModelError::encoder(
                encoder.id(),
                format!(
                    "returned {} results for {} texts",
                    embedded.len(),
                    chunk.len()
                ),
            ));
        }
        for (&i, e) in chunk.iter().zip(embedded) {
            if e.dim != encoder.dim() || e.embeddings.len() != e.tokens.len() * e.dim {
                return Err(ModelError::encoder(
                    encoder.id(),
                    format!(
                        "returned {} values for {} tokens of width {} (declared {}) for {:?}",
                        e.embeddings.len(),
                        e.tokens.len(),
                        e.dim,
                        encoder.dim(),
                        texts[i]
                    ),
                ));
            }
            out[i] = Some(e);
        }
        done += chunk.len() as u64;
        progress(done);
    }
    Ok(out.into_iter().flatten().collect())
}

fn properties() -> WriterProperties {
    let values = ColumnPath::new(vec![col::EMBEDDINGS.into(), "list".into(), "item".into()]);
    WriterProperties::builder()
        .set_compression(Compression::ZSTD(
            ZstdLevel::try_new(3).expect("valid level"),
        ))
        .set_max_row_group_row_count(Some(ROW_GROUP_ROWS))
        // Byte-stream-split groups float bytes by significance, which zstd compresses well.
        .set_column_dictionary_enabled(values.clone(), false)
        .set_column_encoding(values, Encoding::BYTE_STREAM_SPLIT)
        .build()
}

/// Encode one shard (captions and their embeddings, in order) as Parquet bytes.
fn encode_shard(
    encoder: &str,
    dim: usize,
    captions: &[String],
    embeddings: &[TokenEmbeddings],
) -> Result<Vec<u8>, ModelError> {
    let schema = shard_schema(encoder, dim);
    let mut out = Vec::new();
    let failed =
        |e: &dyn std::fmt::Display| ModelError::encoder(encoder, format!("encoding shard: {e}"));
    let mut writer = ArrowWriter::try_new(&mut out, schema.clone(), Some(properties()))
        .map_err(|e| failed(&e))?;
    for (texts, embs) in captions
        .chunks(ROW_GROUP_ROWS)
        .zip(embeddings.chunks(ROW_GROUP_ROWS))
    {
        let mut caption = StringBuilder::new();
        let mut tokens =
            ListBuilder::new(StringBuilder::new()).with_field(list_item(DataType::Utf8));
        let mut num_tokens = UInt32Builder::with_capacity(texts.len());
        let mut values =
            ListBuilder::new(Float32Builder::new()).with_field(list_item(DataType::Float32));
        for (text, e) in texts.iter().zip(embs) {
            caption.append_value(text);
            e.tokens
                .iter()
                .for_each(|t| tokens.values().append_value(t));
            tokens.append(true);
            num_tokens.append_value(e.tokens.len() as u32);
            values.values().append_slice(&e.embeddings);
            values.append(true);
        }
        let columns: Vec<ArrayRef> = vec![
            Arc::new(caption.finish()),
            Arc::new(tokens.finish()),
            Arc::new(num_tokens.finish()),
            Arc::new(values.finish()),
        ];
        let batch = RecordBatch::try_new(schema.clone(), columns).map_err(|e| failed(&e))?;
        writer.write(&batch).map_err(|e| failed(&e))?;
    }
    writer.close().map_err(|e| failed(&e))?;
    Ok(out)
}

struct Shard {
    path: PathBuf,
    bytes: Bytes,
    metadata: ArrowReaderMetadata,
}

/// The caption embeddings of one encoder in a corpus, decoded one caption at a time.
pub struct CaptionEmbeddings {
    encoder: String,
    dim: usize,
    shards: Vec<Shard>,
    /// caption → (shard, row group, row in group).
    index: HashMap<String, (usize, usize, usize)>,
}

impl CaptionEmbeddings {
    /// Open the embeddings that `encoder_id` made for the corpus in `corpus_dir` (as listed
    /// in its manifest); only the caption column is decoded here.
    pub fn open(corpus_dir: &Path, encoder_id: &str) -> Result<Self, ModelError> {
        let manifest = Manifest::read(corpus_dir).map_err(|e| ModelError::corpus(corpus_dir, e))?;
        let entry = manifest
            .text_embeddings
            .iter()
            .find(|e| e.encoder == encoder_id)
            .ok_or_else(|| {
                ModelError::corpus(
                    corpus_dir,
                    format!("no text embeddings by encoder {encoder_id} in manifest.json"),
                )
            })?;
        let dir = corpus_dir.join(&entry.dir);
        let index_path = dir.join(INDEX_FILE);
        let index = read_index(&index_path)?.ok_or_else(|| ModelError::Missing {
            path: index_path.clone(),
            what: "caption embedding index",
        })?;
        let rows: u64 = index.shards.iter().map(|s| s.rows).sum();
        if index.encoder != encoder_id || index.dim != entry.dim || rows != entry.captions {
            return Err(ModelError::invalid(
                &index_path,
                format!(
                    "holds {rows} captions by {} (dim {}), manifest says {} by {encoder_id} (dim {}): rerun embed-text",
                    index.encoder, index.dim, entry.captions, entry.dim
                ),
            ));
        }
        let mut shards = Vec::with_capacity(index.shards.len());
        let mut by_caption = HashMap::with_capacity(rows as usize);
        for (s, shard) in index.shards.iter().enumerate() {
            let path = dir.join(&shard.file);
            let file = std::fs::File::open(&path).map_err(|e| ModelError::io(&path, e))?;
            // SAFETY: shards are written once (temp + rename) and never modified in place.
            let map = unsafe { memmap2::Mmap::map(&file) }.map_err(|e| ModelError::io(&path, e))?;
            let bytes = Bytes::from_owner(map);
            let metadata = ArrowReaderMetadata::load(&bytes, ArrowReaderOptions::new())
                .map_err(|e| ModelError::invalid(&path, e))?;
            let meta = metadata.schema().metadata();
            if meta.get(META_ENCODER).map(String::as_str) != Some(encoder_id)
                || meta.get(META_DIM) != Some(&index.dim.to_string())
            {
                return Err(ModelError::invalid(
                    &path,
                    format!(
                        "schema metadata {meta:?} is not encoder {encoder_id}, dim {}",
                        index.dim
                    ),
                ));
            }
            let shard = Shard {
                path,
                bytes,
                metadata,
            };
            let mut group_rows = shard
                .metadata
                .metadata()
                .row_groups()
                .iter()
                .enumerate()
                .flat_map(|(g, rg)| (0..rg.num_rows() as usize).map(move |r| (g, r)));
            for batch in shard.reader(&[col::CAPTION], None, None)? {
                let batch = batch.map_err(|e| ModelError::invalid(&shard.path, e))?;
                let texts = batch
                    .column(0)
                    .as_string_opt::<i32>()
                    .ok_or_else(|| ModelError::invalid(&shard.path, "caption is not utf8"))?;
                for text in texts.iter() {
                    let (g, r) = group_rows.next().ok_or_else(|| {
                        ModelError::invalid(&shard.path, "more rows than its metadata lists")
                    })?;
                    let text =
                        text.ok_or_else(|| ModelError::invalid(&shard.path, "null caption"))?;
                    by_caption.insert(text.to_string(), (s, g, r));
                }
            }
            shards.push(shard);
        }
        Ok(Self {
            encoder: encoder_id.to_string(),
            dim: index.dim,
            shards,
            index: by_caption,
        })
    }

    /// Encoder id.
    pub fn encoder(&self) -> &str {
        &self.encoder
    }

    /// Embedding width.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Number of captions.
    pub fn len(&self) -> usize {
        self.index.len()
    }

    /// Whether no caption is held.
    pub fn is_empty(&self) -> bool {
        self.index.is_empty()
    }

    /// The token embeddings of `caption`, or `None` when it was not embedded.
    pub fn get(&self, caption: &str) -> Result<Option<TokenEmbeddings>, ModelError> {
        let Some(&(s, group, row)) = self.index.get(caption) else {
            return Ok(None);
        };
        let shard = &self.shards[s];
        let batch = shard
            .reader(&[col::TOKENS, col::EMBEDDINGS], Some(group), Some(row))?
            .next()
            .ok_or_else(|| {
                ModelError::invalid(
                    &shard.path,
                    format!("row {row} of row group {group} missing"),
                )
            })?
            .map_err(|e| ModelError::invalid(&shard.path, e))?;
        self.row_embeddings(shard, &batch, 0, caption).map(Some)
    }

    /// The token embeddings of every caption of `captions` that was embedded, reading each
    /// row group that holds one once: a lookup per caption decompresses its whole page again
    /// for every caption, seconds for a corpus's worth.
    pub fn get_many<'a>(
        &self,
        captions: impl IntoIterator<Item = &'a str>,
    ) -> Result<HashMap<String, TokenEmbeddings>, ModelError> {
        // (shard, row group) → (row in group, caption), sorted by row.
        let mut wanted: BTreeMap<(usize, usize), Vec<(usize, &str)>> = BTreeMap::new();
        for caption in captions {
            if let Some(&(s, group, row)) = self.index.get(caption) {
                wanted.entry((s, group)).or_default().push((row, caption));
            }
        }
        let mut out = HashMap::new();
        for ((s, group), mut rows) in wanted {
            rows.sort_unstable();
            rows.dedup();
            let shard = &self.shards[s];
            let mut first = 0;
            let mut next = rows.iter().peekable();
            for batch in shard.reader(&[col::TOKENS, col::EMBEDDINGS], Some(group), None)? {
                let batch = batch.map_err(|e| ModelError::invalid(&shard.path, e))?;
                while let Some(&&(row, caption)) = next.peek() {
                    if row >= first + batch.num_rows() {
                        break;
                    }
                    let emb = self.row_embeddings(shard, &batch, row - first, caption)?;
                    out.insert(caption.to_string(), emb);
                    next.next();
                }
                first += batch.num_rows();
            }
        }
        Ok(out)
    }

    /// The token embeddings in row `row` of `batch` (columns tokens and embeddings), which
    /// hold `caption`'s.
    fn row_embeddings(
        &self,
        shard: &Shard,
        batch: &RecordBatch,
        row: usize,
        caption: &str,
    ) -> Result<TokenEmbeddings, ModelError> {
        let bad = |e: &dyn std::fmt::Display| ModelError::invalid(&shard.path, e);
        let tokens = batch
            .column_by_name(col::TOKENS)
            .and_then(|c| c.as_list_opt::<i32>())
            .map(|l| l.value(row))
            .ok_or_else(|| bad(&"tokens is not a list"))?;
        let tokens: Vec<String> = tokens
            .as_string_opt::<i32>()
            .ok_or_else(|| bad(&"tokens are not utf8"))?
            .iter()
            .map(|t| t.unwrap_or_default().to_string())
            .collect();
        let values = batch
            .column_by_name(col::EMBEDDINGS)
            .and_then(|c| c.as_list_opt::<i32>())
            .map(|l| l.value(row))
            .ok_or_else(|| bad(&"embeddings is not a list"))?;
        let embeddings = values
            .as_primitive_opt::<Float32Type>()
            .ok_or_else(|| bad(&"embeddings are not f32"))?
            .values()
            .to_vec();
        if embeddings.len() != tokens.len() * self.dim {
            return Err(bad(&format!(
                "{caption:?}: {} values for {} tokens of width {}",
                embeddings.len(),
                tokens.len(),
                self.dim
            )));
        }
        Ok(TokenEmbeddings {
            tokens,
            embeddings,
            dim: self.dim,
        })
    }
}

impl Shard {
    /// A reader of `columns`: of the whole shard, or of row group `group`, or of row `row`
    /// of that group.
    fn reader(
        &self,
        columns: &[&str],
        group: Option<usize>,
        row: Option<usize>,
    ) -> Result<parquet::arrow::arrow_reader::ParquetRecordBatchReader, ModelError> {
        let mask = projection(
            self.metadata.parquet_schema(),
            self.metadata.schema(),
            columns,
        );
        let mut builder = ParquetRecordBatchReaderBuilder::new_with_metadata(
            self.bytes.clone(),
            self.metadata.clone(),
        )
        .with_projection(mask);
        if let Some(group) = group {
            builder = builder.with_row_groups(vec![group]);
        }
        if let Some(r) = row {
            builder = builder.with_row_selection(RowSelection::from(vec![
                RowSelector::skip(r),
                RowSelector::select(1),
            ]));
        }
        builder
            .build()
            .map_err(|e| ModelError::invalid(&self.path, e))
    }
}

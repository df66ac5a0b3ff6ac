//! Little-endian encoding of bake payloads. Every length a reader is given
//! is checked against the bytes left before anything is allocated, so a
//! corrupt or hostile file fails with a message instead of exhausting memory.

use crate::TechniqueError;
use glam::Vec3;

/// Appends little-endian values to a payload.
#[derive(Default)]
pub struct PayloadWriter {
    pub bytes: Vec<u8>,
}

impl PayloadWriter {
    pub fn with_capacity(capacity: usize) -> Self {
        Self {
            bytes: Vec::with_capacity(capacity),
        }
    }
    pub fn u32(&mut self, value: u32) {
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }
    pub fn f32(&mut self, value: f32) {
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }
    pub fn u64(&mut self, value: u64) {
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }
    pub fn f64(&mut self, value: f64) {
        self.bytes.extend_from_slice(&value.to_le_bytes());
    }
    /// A length-prefixed list of u32.
    pub fn u32s(&mut self, values: &[u32]) {
        self.u32(values.len() as u32);
        for value in values {
            self.u32(*value);
        }
    }
    /// A length-prefixed list of f32.
    pub fn f32s(&mut self, values: &[f32]) {
        self.u32(values.len() as u32);
        for value in values {
            self.f32(*value);
        }
    }
    /// A length-prefixed list of vectors.
    pub fn vectors(&mut self, values: &[Vec3]) {
        self.u32(values.len() as u32);
        for value in values {
            for component in value.to_array() {
                self.f32(component);
            }
        }
    }
    /// A length-prefixed list of f16 bit patterns.
    pub fn halves(&mut self, values: &[u16]) {
        self.u32(values.len() as u32);
        for value in values {
            self.bytes.extend_from_slice(&value.to_le_bytes());
        }
    }
    pub fn finish(self) -> Vec<u8> {
        self.bytes
    }
}

/// Reads what [`PayloadWriter`] wrote; `technique` names the bake in errors.
pub struct PayloadReader<'a> {
    bytes: &'a [u8],
    cursor: usize,
    technique: &'static str,
}

impl<'a> PayloadReader<'a> {
    pub fn new(bytes: &'a [u8], technique: &'static str) -> Self {
        Self {
            bytes,
            cursor: 0,
            technique,
        }
    }

    /// The error for a payload that is not what its sizes say.
    pub fn corrupt(&self, message: &str) -> TechniqueError {
        TechniqueError::Other(format!(
            "{} bake is corrupt: {message}; bake it again",
            self.technique.to_uppercase()
        ))
    }

    fn take(&mut self, count: usize) -> Result<&'a [u8], TechniqueError> {
        let end = self
            .cursor
            .checked_add(count)
            .ok_or_else(|| self.corrupt("a length overflows"))?;
        let slice = self
            .bytes
            .get(self.cursor..end)
            .ok_or_else(|| self.corrupt("truncated"))?;
        self.cursor = end;
        Ok(slice)
    }

    pub fn u32(&mut self) -> Result<u32, TechniqueError> {
        Ok(u32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }

    pub fn f32(&mut self) -> Result<f32, TechniqueError> {
        Ok(f32::from_le_bytes(
            self.take(4)?.try_into().expect("4 bytes"),
        ))
    }

    pub fn u64(&mut self) -> Result<u64, TechniqueError> {
        Ok(u64::from_le_bytes(
            self.take(8)?.try_into().expect("8 bytes"),
        ))
    }

    /// A finite f64.
    pub fn f64(&mut self) -> Result<f64, TechniqueError> {
        let value = f64::from_le_bytes(self.take(8)?.try_into().expect("8 bytes"));
        if value.is_finite() {
            Ok(value)
        } else {
            Err(self.corrupt("a number is not finite"))
        }
    }

    /// Reads the payload's version; fails unless it is `expected`, naming
    /// `what` the payload is and what to do about it.
    pub fn version(
        &mut self,
        expected: u32,
        what: &str,
        remedy: &str,
    ) -> Result<(), TechniqueError> {
        let version = self.u32()?;
        if version == expected {
            Ok(())
        } else {
            Err(self.corrupt(&format!(
                "{what} version {version}, this relight reads {expected}: {remedy}"
            )))
        }
    }

    /// A finite f32.
    pub fn finite(&mut self) -> Result<f32, TechniqueError> {
        let value = self.f32()?;
        if value.is_finite() {
            Ok(value)
        } else {
            Err(self.corrupt("a number is not finite"))
        }
    }

    /// A length prefix whose `element_bytes`-sized elements fit in what is left.
    fn length(&mut self, element_bytes: usize) -> Result<usize, TechniqueError> {
        let count = self.u32()? as usize;
        if count.saturating_mul(element_bytes) > self.bytes.len() - self.cursor {
            return Err(self.corrupt("a list is longer than the payload"));
        }
        Ok(count)
    }

    pub fn u32s(&mut self) -> Result<Vec<u32>, TechniqueError> {
        let count = self.length(4)?;
        let bytes = self.take(count * 4)?;
        Ok(bytes
            .chunks_exact(4)
            .map(|chunk| u32::from_le_bytes(chunk.try_into().expect("4 bytes")))
            .collect())
    }

    pub fn f32s(&mut self) -> Result<Vec<f32>, TechniqueError> {
        let count = self.length(4)?;
        let bytes = self.take(count * 4)?;
        let values: Vec<f32> = bytes
            .chunks_exact(4)
            .map(|chunk| f32::from_le_bytes(chunk.try_into().expect("4 bytes")))
            .collect();
        if values.iter().any(|value| !value.is_finite()) {
            return Err(self.corrupt("a number is not finite"));
        }
        Ok(values)
    }

    pub fn vectors(&mut self) -> Result<Vec<Vec3>, TechniqueError> {
        let count = self.length(12)?;
        let bytes = self.take(count * 12)?;
        let values: Vec<Vec3> = bytes
            .chunks_exact(12)
            .map(|chunk| {
                let component =
                    |at: usize| f32::from_le_bytes(chunk[at..at + 4].try_into().expect("4 bytes"));
                Vec3::new(component(0), component(4), component(8))
            })
            .collect();
        if values.iter().any(|value| !value.is_finite()) {
            return Err(self.corrupt("a position or direction is not finite"));
        }
        Ok(values)
    }

    pub fn halves(&mut self) -> Result<Vec<u16>, TechniqueError> {
        let count = self.length(2)?;
        let bytes = self.take(count * 2)?;
        Ok(bytes
            .chunks_exact(2)
            .map(|chunk| u16::from_le_bytes([chunk[0], chunk[1]]))
            .collect())
    }

    /// Fails unless every byte was read.
    pub fn end(&self) -> Result<(), TechniqueError> {
        if self.cursor == self.bytes.len() {
            Ok(())
        } else {
            Err(self.corrupt("trailing bytes"))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_hostile_lengths() {
        let mut writer = PayloadWriter::default();
        writer.u32(7);
        writer.f32s(&[1.5, -2.0]);
        writer.vectors(&[Vec3::new(1.0, 2.0, 3.0)]);
        writer.halves(&[0x3c00]);
        writer.u32s(&[9, 10]);
        let bytes = writer.finish();
        let mut reader = PayloadReader::new(&bytes, "srp");
        assert_eq!(reader.u32().unwrap(), 7);
        assert_eq!(reader.f32s().unwrap(), vec![1.5, -2.0]);
        assert_eq!(reader.vectors().unwrap(), vec![Vec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(reader.halves().unwrap(), vec![0x3c00]);
        assert_eq!(reader.u32s().unwrap(), vec![9, 10]);
        reader.end().unwrap();

        // A length of four billion elements is refused before allocating.
        let hostile = u32::MAX.to_le_bytes();
        let error = PayloadReader::new(&hostile, "srp").f32s().unwrap_err();
        assert!(error.to_string().contains("SRP bake is corrupt"), "{error}");
    }
}

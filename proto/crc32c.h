#pragma once

// CRC32C (Castagnoli polynomial 0x1EDC6F41, reflected 0x82F63B78, initial value and final
// XOR 0xFFFFFFFF), the checksum of every wire frame. Uses the SSE4.2 crc32 instruction when
// the CPU has it (checked once at run time) and a slicing-by-8 table implementation
// otherwise; both give identical results. Check value: Crc32c("123456789") == 0xE3069283.

#include <cstddef>
#include <cstdint>
#include <span>

namespace ccmd {

// CRC32C of a byte range.
std::uint32_t Crc32c(const void* data, std::size_t size);
inline std::uint32_t Crc32c(std::span<const std::uint8_t> bytes) {
  return Crc32c(bytes.data(), bytes.size());
}

// Continues a CRC over more bytes: Crc32cExtend(Crc32c(a), b) == Crc32c(a followed by b).
std::uint32_t Crc32cExtend(std::uint32_t crc, const void* data, std::size_t size);

// The two implementations, exposed so that tests can compare them.
std::uint32_t Crc32cExtendSoftware(std::uint32_t crc, const void* data, std::size_t size);
// Precondition: Crc32cHardwareAvailable().
std::uint32_t Crc32cExtendHardware(std::uint32_t crc, const void* data, std::size_t size);
bool Crc32cHardwareAvailable();

}  // namespace ccmd

#include "proto/crc32c.h"

#include <cstdint>
#include <cstring>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/random.h"

namespace ccmd {
namespace {

TEST(Crc32cTest, StandardCheckValue) {
  const char* text = "123456789";
  EXPECT_EQ(Crc32c(text, std::strlen(text)), 0xE3069283u);
  EXPECT_EQ(Crc32cExtendSoftware(0, text, 9), 0xE3069283u);
  EXPECT_EQ(Crc32c(text, 0), 0u);
}

// Test vectors of RFC 3720 (iSCSI), appendix B.4.
TEST(Crc32cTest, Rfc3720Vectors) {
  std::vector<std::uint8_t> zeros(32, 0x00), ones(32, 0xFF), up(32), down(32);
  for (int i = 0; i < 32; ++i) {
    up[i] = static_cast<std::uint8_t>(i);
    down[i] = static_cast<std::uint8_t>(31 - i);
  }
  EXPECT_EQ(Crc32c(zeros), 0x8A9136AAu);
  EXPECT_EQ(Crc32c(ones), 0x62A8AB43u);
  EXPECT_EQ(Crc32c(up), 0x46DD794Eu);
  EXPECT_EQ(Crc32c(down), 0x113FDB5Cu);
}

TEST(Crc32cTest, SoftwareAndHardwareAgreeOnEveryLengthAndAlignment) {
  Rng rng(42);
  std::vector<std::uint8_t> data(300);
  for (auto& b : data) b = static_cast<std::uint8_t>(rng.Next());
  for (std::size_t offset = 0; offset < 8; ++offset) {
    for (std::size_t n = 0; n + offset <= data.size(); n += 7) {
      const std::uint32_t sw = Crc32cExtendSoftware(0, data.data() + offset, n);
      EXPECT_EQ(Crc32c(data.data() + offset, n), sw);
      if (Crc32cHardwareAvailable()) {
        EXPECT_EQ(Crc32cExtendHardware(0, data.data() + offset, n), sw);
      }
    }
  }
}

TEST(Crc32cTest, ExtendEqualsOneShot) {
  const char* text = "123456789";
  for (std::size_t split = 0; split <= 9; ++split) {
    EXPECT_EQ(Crc32cExtend(Crc32c(text, split), text + split, 9 - split), 0xE3069283u);
    EXPECT_EQ(Crc32cExtendSoftware(Crc32cExtendSoftware(0, text, split), text + split, 9 - split),
              0xE3069283u);
  }
}

}  // namespace
}  // namespace ccmd

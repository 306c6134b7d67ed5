#include "libccmd/util/string_util.h"

#include <gtest/gtest.h>

namespace ccmd {
namespace {

TEST(StringUtilTest, ParseRejectsPartialNumbers) {
  EXPECT_EQ(*ParseDouble(" 1.5 "), 1.5);
  EXPECT_FALSE(ParseDouble("1.5x").ok());
  EXPECT_FALSE(ParseDouble("").ok());
  EXPECT_FALSE(ParseDouble("nan").ok());
  EXPECT_EQ(*ParseInt("-12"), -12);
  EXPECT_FALSE(ParseInt("3.0").ok());
}

TEST(StringUtilTest, SplitWhitespaceHandlesTabsAndRuns) {
  const auto parts = SplitWhitespace("  1305031453.3 \t rgb/a.png\r");
  ASSERT_EQ(parts.size(), 2u);
  EXPECT_EQ(parts[0], "1305031453.3");
  EXPECT_EQ(parts[1], "rgb/a.png");
}

TEST(StringUtilTest, FormatBytesUsesDecimalUnits) {
  EXPECT_EQ(FormatBytes(999), "999 B");
  EXPECT_EQ(FormatBytes(58800), "58.8 kB");
  EXPECT_EQ(FormatBytes(2.05e6), "2.0 MB");
}

}  // namespace
}  // namespace ccmd

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

// Blank and '#' lines are skipped but counted, Windows line ends read as Unix ones, and the
// first error names its file and line and stops the walk.
TEST(StringUtilTest, DataLinesSkipCommentsAndErrorsNameTheLine) {
  std::vector<std::string> first_fields;
  int calls = 0;
  const Status status =
      ForEachDataLine("# header\r\n\n  1.0 a.png\r\n\t\n2.0\n3.0 c.png\n", "rgb.txt",
                      [&](const std::vector<std::string_view>& fields) -> Status {
                        ++calls;
                        first_fields.emplace_back(fields[0]);
                        if (fields.size() < 2) return Corrupt("expected 'timestamp path'");
                        return Status::Ok();
                      });
  EXPECT_EQ(calls, 2);
  EXPECT_EQ(first_fields, (std::vector<std::string>{"1.0", "2.0"}));
  EXPECT_EQ(status.code(), StatusCode::kCorrupt);
  EXPECT_EQ(status.message(), "rgb.txt:5: expected 'timestamp path'");
  EXPECT_TRUE(ForEachDataLine("", "empty", [](const auto&) -> Status {
                return Corrupt("never called");
              }).ok());
}

TEST(StringUtilTest, FormatBytesUsesDecimalUnits) {
  EXPECT_EQ(FormatBytes(999), "999 B");
  EXPECT_EQ(FormatBytes(58800), "58.8 kB");
  EXPECT_EQ(FormatBytes(2.05e6), "2.0 MB");
}

}  // namespace
}  // namespace ccmd

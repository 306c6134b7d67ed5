// The sizes the code is held to, so that each part stays readable on its own: no source file
// in libccmd over 800 lines, and no function of the back-end (libccmd/backend) over 80 lines,
// counted from the first line of its signature to its closing brace.

#include <algorithm>
#include <filesystem>
#include <sstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "libccmd/util/file_util.h"

namespace {

constexpr int kMaxFileLines = 800;
constexpr int kMaxBackendFunctionLines = 80;

std::vector<std::string> Lines(const std::string& text) {
  std::vector<std::string> lines;
  std::istringstream in(text);
  for (std::string line; std::getline(in, line);) lines.push_back(line);
  return lines;
}

// The file's lines; a file that cannot be read fails the test.
std::vector<std::string> FileLines(const std::filesystem::path& path) {
  const auto text = ccmd::ReadFileToString(path.string());
  EXPECT_TRUE(text.ok()) << path.string() << ": " << text.status().ToString();
  return text.ok() ? Lines(*text) : std::vector<std::string>{};
}

bool StartsWith(const std::string& s, const std::string& prefix) {
  return s.compare(0, prefix.size(), prefix) == 0;
}

struct FunctionSpan {
  int first_line = 0;  // 1-based
  int lines = 0;
  std::string signature;
  bool body_on_own_lines = false;  // else on the line that opens it
};

// Function definitions of a clang-formatted file (namespaces not indented): a signature starts
// at column 0 and the body closes with a brace at column 0.
std::vector<FunctionSpan> FunctionSpans(const std::vector<std::string>& lines) {
  std::vector<FunctionSpan> spans;
  const auto not_a_signature = [](const std::string& l) {
    if (l.empty() || l[0] == ' ' || l[0] == '\t' || l[0] == '#' || l[0] == '}') return true;
    for (const char* p : {"//", "namespace", "using ", "struct ", "class ", "enum ", "template <",
                          "static_assert", "extern "}) {
      if (StartsWith(l, p)) return true;
    }
    return l.find('(') == std::string::npos;
  };
  for (std::size_t i = 0; i < lines.size(); ++i) {
    if (not_a_signature(lines[i])) continue;
    std::size_t open = i;
    while (open < lines.size() && lines[open].find('{') == std::string::npos &&
           (lines[open].empty() || lines[open].back() != ';')) {
      ++open;
    }
    if (open == lines.size() || lines[open].back() == ';') {
      i = open;  // a declaration
      continue;
    }
    std::size_t close = open;
    const std::string& o = lines[open];
    if (o.find('}') == std::string::npos || o.rfind('}') < o.find('{')) {
      for (close = open + 1; close < lines.size() && !StartsWith(lines[close], "}"); ++close) {
      }
    }
    if (close == lines.size()) break;
    if (close > open && lines[close] != "}") {  // "};": a class or an initialiser
      i = close;
      continue;
    }
    spans.push_back(
        {static_cast<int>(i) + 1, static_cast<int>(close - i) + 1, lines[i], close > open});
    i = close;
  }
  return spans;
}

std::vector<std::filesystem::path> SourcesUnder(const std::filesystem::path& dir) {
  std::vector<std::filesystem::path> files;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir)) {
    const std::string ext = entry.path().extension().string();
    if (entry.is_regular_file() && (ext == ".cc" || ext == ".h")) files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

TEST(SourceLimitsTest, FunctionSpansAreFoundAsWritten) {
  std::string text =
      "namespace ccmd {\n"
      "\n"
      "// A comment (with parentheses).\n"
      "int Declared(int a);\n"
      "int OneLine() { return 1; }\n"
      "StatusOr<Thing> Long(int a,\n"
      "                     int b) {\n";
  for (int i = 0; i < 90; ++i) text += "  x += " + std::to_string(i) + ";\n";
  text +=
      "}\n"
      "\n"
      "struct S {\n"
      "  void Method() {}\n"
      "};\n"
      "\n"
      "void Short() {\n"
      "  if (a) {\n"
      "  }\n"
      "}\n"
      "\n"
      "}  // namespace ccmd\n";
  const std::vector<FunctionSpan> spans = FunctionSpans(Lines(text));
  ASSERT_EQ(spans.size(), 3u);
  EXPECT_EQ(spans[0].first_line, 5);
  EXPECT_EQ(spans[0].lines, 1);
  EXPECT_EQ(spans[1].first_line, 6);
  EXPECT_EQ(spans[1].lines, 93);  // two signature lines, 90 statements, the brace
  EXPECT_EQ(spans[2].lines, 4);
}

TEST(SourceLimitsTest, NoLibccmdFileIsOver800Lines) {
  const std::filesystem::path root = std::filesystem::path(CCMD_SOURCE_DIR) / "libccmd";
  const std::vector<std::filesystem::path> files = SourcesUnder(root);
  ASSERT_GT(files.size(), 50u) << "libccmd sources not found under " << root;
  for (const auto& file : files) {
    const int lines = static_cast<int>(FileLines(file).size());
    EXPECT_LE(lines, kMaxFileLines) << file.string() << " has " << lines << " lines";
  }
}

TEST(SourceLimitsTest, NoBackendFunctionIsOver80Lines) {
  const std::filesystem::path root = std::filesystem::path(CCMD_SOURCE_DIR) / "libccmd/backend";
  const std::vector<std::filesystem::path> files = SourcesUnder(root);
  ASSERT_GT(files.size(), 10u) << "back-end sources not found under " << root;
  for (const auto& file : files) {
    const std::vector<std::string> lines = FileLines(file);
    int bodies = 0;
    for (const FunctionSpan& f : FunctionSpans(lines)) {
      bodies += f.body_on_own_lines;
      EXPECT_LE(f.lines, kMaxBackendFunctionLines)
          << file.string() << ":" << f.first_line << " (" << f.signature << ") has " << f.lines
          << " lines";
    }
    // Every body on lines of its own closes with a lone brace: none was missed.
    EXPECT_EQ(bodies, std::count(lines.begin(), lines.end(), "}")) << file.string();
  }
}

}  // namespace

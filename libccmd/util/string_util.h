#pragma once

#include <functional>
#include <string>
#include <string_view>
#include <vector>

#include "libccmd/util/status.h"

namespace ccmd {

std::string_view Trim(std::string_view text);

// Splits on runs of spaces and tabs (the TUM list and trajectory format).
std::vector<std::string_view> SplitWhitespace(std::string_view text);

std::vector<std::string> Split(std::string_view text, char separator);

// Calls `line` with the whitespace-separated fields of each line of `text` that is neither
// blank nor a '#' comment, and with "NAME:LINE" for its messages; the first error it returns
// stops the walk and is returned with that location added.
Status ForEachDataLine(
    std::string_view text, const std::string& name,
    const std::function<Status(const std::vector<std::string_view>& fields)>& line);

bool StartsWith(std::string_view text, std::string_view prefix);

// Whole-token numeric parsing: "1.5x" and "" are errors, not 1.5 and 0.
StatusOr<double> ParseDouble(std::string_view text);
StatusOr<long long> ParseInt(std::string_view text);

// The shortest decimal text that reads back as exactly `value` ("481.2", "1e-07"), for files
// that other programs read again (configs).
std::string ExactNumber(double value);

// Human-readable byte count: "1.5 MB".
std::string FormatBytes(double bytes);

}  // namespace ccmd

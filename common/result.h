// ============================================================================
//  flarelab common: Error, Result<T>
// ============================================================================
//
// What can fail on outside input (a file, a device, a request) returns Result<T>: either a T or
// an Error naming what was wrong. The API follows std::expected (has_value, value, error,
// operator*, operator->, explicit bool) so that Result can become an alias once the compiler
// ships <expected>. No exceptions cross a library boundary.
#pragma once

#include <cstdlib>
#include <string>
#include <type_traits>
#include <utility>
#include <variant>

namespace flarelab {

enum class ErrorCode {
    InvalidArgument,  // a parameter out of its documented range
    ParseError,       // a file or request that does not follow its format
    NotFound,         // a file or device that does not exist
    IoError,          // the operating system refused a read or write
    Unsupported,      // a valid request the program cannot serve
    Internal,         // a computation that failed where it should not (a bug or bad numerics)
};

inline const char* errorCodeName(ErrorCode code) {
    switch (code) {
        case ErrorCode::InvalidArgument:
            return "invalid argument";
        case ErrorCode::ParseError:
            return "parse error";
        case ErrorCode::NotFound:
            return "not found";
        case ErrorCode::IoError:
            return "i/o error";
        case ErrorCode::Unsupported:
            return "unsupported";
        case ErrorCode::Internal:
            return "internal error";
    }
    return "error";
}

struct Error {
    ErrorCode code = ErrorCode::Internal;
    std::string message;  // names the file, line, column or field at fault

    // The message with context prepended, e.g. "while loading lens: " + message.
    Error withContext(const std::string& context) const {
        return Error{code, context + ": " + message};
    }
};

template <typename T>
class [[nodiscard]] Result {
public:
    using value_type = T;

    Result(const T& value) : storage_(std::in_place_index<0>, value) {}          // NOLINT
    Result(T&& value) : storage_(std::in_place_index<0>, std::move(value)) {}    // NOLINT
    Result(Error error) : storage_(std::in_place_index<1>, std::move(error)) {}  // NOLINT

    bool has_value() const { return storage_.index() == 0; }
    explicit operator bool() const { return has_value(); }

    T& value() & {
        checkValue();
        return std::get<0>(storage_);
    }
    const T& value() const& {
        checkValue();
        return std::get<0>(storage_);
    }
    T&& value() && {
        checkValue();
        return std::get<0>(std::move(storage_));
    }
    const Error& error() const {
        if (has_value()) std::abort();  // asking a success for its error is a bug
        return std::get<1>(storage_);
    }
    T& operator*() & { return value(); }
    const T& operator*() const& { return value(); }
    T* operator->() { return &value(); }
    const T* operator->() const { return &value(); }

private:
    void checkValue() const {
        if (!has_value()) std::abort();  // callers test before they take the value
    }
    std::variant<T, Error> storage_;
};

// Result<void>: success carries nothing.
struct Ok {};
using Status = Result<Ok>;

inline Error makeError(ErrorCode code, std::string message) {
    return Error{code, std::move(message)};
}

}  // namespace flarelab
